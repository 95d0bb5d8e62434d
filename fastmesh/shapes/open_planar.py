"""Open piecewise-planar inputs rebuilt exactly: a ramp, a roof without its floor, a box without its lid.

``planar.polyhedron`` rebuilds a closed polyhedron: every face of a plane ends where a neighbouring plane cuts
it.  An open surface has edges no plane ends: where the surface stops.  A game prop's open side almost always lies
on a side of its bounding box (the floor under a ramp, the top of a tray), so that side stands in as a plane with
no points: it bounds the faces of the planes that reach it and gets no face of its own.  The result is kept only
where every open edge lies on such a side and the surface and the points explain each other both ways, as for a
closed one; anything else gives None.
"""

from __future__ import annotations

import numpy as np

from .planar import PlanarConfig, _explains, planar_mesh

PARALLEL_COS = np.cos(np.radians(10))  # as ``planar.neighbour_planes``: planes closer than this never meet
EDGE_SHARE = 0.3  # a plane's open edge on a box side spans at least this share of the plane's width along it


def open_polyhedron(points: np.ndarray, normals: np.ndarray, cfg: PlanarConfig = PlanarConfig()
                    ) -> tuple[np.ndarray, np.ndarray] | None:
    """The open piecewise-planar surface of an oriented point cloud whose open edges lie on its bounding box's
    sides, or None where it is not one.

    Parameters
    ----------
    points : (N, 3) float, in the unit frame (``shape.Normalization``), the open sides along its axes
    normals : (N, 3) float, unit, on the side the faces face
    cfg : tolerances, as ``planar.polyhedron``

    Returns
    -------
    (V, 3) float64 vertices and (F, 3) int64 faces, edge-manifold and consistently oriented, with at least one
    open edge and every open edge on a side of the points' bounding box; or None.
    """
    made = planar_mesh(points, normals, cfg, cut=_cut_at_box)
    if made is None:
        return None
    vertices, faces, pts, reach, sides = made
    if not _open_on_sides(vertices, faces, sides, cfg.tolerance) or not _explains(vertices, faces, pts, reach):
        return None
    return vertices, faces


def _cut_at_box(points: np.ndarray, planes: np.ndarray, labels: np.ndarray, near: list[set[int]], reach: float
                ) -> tuple[np.ndarray | None, list[list[int]] | None]:
    """``planar.planar_mesh``'s ``cut``: the box sides no plane lies on, and for each plane those where it stops
    (``_open_sides``)."""
    sides = box_sides(points, planes, reach)
    if not len(sides):
        return None, None
    return sides, [_open_sides(planes[k], sides, planes[sorted(near[k])], points[labels == k], reach)
                   for k in range(len(planes))]


def box_sides(points: np.ndarray, planes: np.ndarray, reach: float) -> np.ndarray:
    """(S, 4) the sides of the points' axis-aligned bounding box (outward normal n, offset d: n.x = d) that no
    plane of ``planes`` (K, 4) lies on: where an open surface may stop."""
    lo, hi = points.min(0), points.max(0)
    out = []
    for axis in range(3):
        for sign, at in ((-1.0, lo[axis]), (1.0, hi[axis])):
            n = np.zeros(3)
            n[axis] = sign
            d = sign * at
            on = (np.abs(planes[:, :3] @ n) > PARALLEL_COS) & (np.abs(planes[:, :3] @ (n * d) - planes[:, 3]) < reach)
            if not on.any():
                out.append(np.r_[n, d])
    return np.array(out).reshape(-1, 4)


def _open_sides(plane: np.ndarray, sides: np.ndarray, neighbours: np.ndarray, points: np.ndarray, reach: float
                ) -> list[int]:
    """The indices of the box ``sides`` (S, 4) where a plane's surface stops: those it is not parallel to whose
    line its ``points`` follow across ``EDGE_SHARE`` of the plane's width at least (not a corner touching the
    side, as a gable's apex), where that line does not run along a real edge instead (a ridge touching the box:
    along the line where it meets one of its ``neighbours`` (K, 4)) nor along a side already taken (an eave on a
    box's edge reaches two sides: the one crossing the plane more steeply is taken)."""
    order = np.argsort(-np.linalg.norm(np.cross(plane[:3], sides[:, :3]), axis=1))
    taken: list[int] = []
    for j in order:
        side = sides[j]
        if abs(plane[:3] @ side[:3]) > PARALLEL_COS:
            continue
        at = points[np.abs(points @ side[:3] - side[3]) < reach]
        u = np.cross(plane[:3], side[:3])
        if len(at) < 3 or np.ptp(at @ u) < max(EDGE_SHARE * np.ptp(points @ u), reach * np.linalg.norm(u)):
            continue
        others = np.vstack([neighbours, sides[taken]])
        if len(others) and _along(plane, side, at.mean(0), others, reach):
            continue
        taken.append(int(j))
    return taken


def _along(plane: np.ndarray, side: np.ndarray, near: np.ndarray, others: np.ndarray, reach: float) -> bool:
    """Whether the line where ``plane`` meets ``side`` runs along the line where it meets one of ``others`` (K, 4):
    within 10 degrees of it and, at the point of the line nearest ``near`` (3,), within ``reach`` of it."""
    n = plane[:3]
    u = np.cross(n, side[:3])
    u /= np.linalg.norm(u)
    p = np.linalg.solve(np.array([n, side[:3], u]), np.array([plane[3], side[3], u @ near]))
    w = np.cross(n, others[:, :3])
    sine = np.linalg.norm(w, axis=1)
    parallel = np.linalg.norm(np.cross(u, w / np.maximum(sine, 1e-12)[:, None]), axis=1) < np.sin(np.radians(10))
    return bool((parallel & (np.abs(others[:, :3] @ p - others[:, 3]) < reach * sine)).any())


def _open_on_sides(vertices: np.ndarray, faces: np.ndarray, sides: np.ndarray, tol: float) -> bool:
    """Whether ``faces`` are edge-manifold and consistently oriented, with open edges, each on one of ``sides``."""
    e = np.c_[faces.ravel(), faces[:, [1, 2, 0]].ravel()]
    if len(np.unique(e, axis=0)) != len(e):
        return False
    edges, count = np.unique(np.sort(e, axis=1), axis=0, return_counts=True)
    if (count > 2).any() or not (count == 1).any():
        return False
    ends = vertices[edges[count == 1]]  # (B, 2, 3)
    off = np.abs(ends @ sides[:, :3].T - sides[:, 3])  # (B, 2, S)
    return bool((off.max(1) < tol).any(1).all())
