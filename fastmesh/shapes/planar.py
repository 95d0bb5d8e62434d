"""Piecewise-planar inputs rebuilt exactly: the planes found in the points, each plane's faces cut from the
arrangement of its neighbours' lines, corners where three planes meet.

A box, an L block or an extruded outline given as points is a handful of planes; its artist mesh is the
polyhedron they bound, with a vertex exactly where three of them meet.  The decoder places vertices on a grid
of 128 cells and only sees such shapes in the poses of its training data; this stage needs neither.  It follows
PolyFit (Nan and Wonka, 2017): candidate faces from the arrangement of the planes' intersection lines, here each
chosen by whether the plane's own points cover it (:mod:`.arrangement`), and the result kept only where it is
closed and explains the points both ways (``polyhedron``).  A scan's planes hold its points at its own noise,
read from the points (``noise.noise_level``), where each plane's points spread off it as that noise does and no
more (a curved scan's facets spread their points across their width).  Anything else (a curved part, a face the
points do not decide) gives None, and the networks make the mesh.
"""

from __future__ import annotations

from collections.abc import Callable, Collection
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from .arrangement import (
    PLACED_SNAP,
    Cell,
    chosen,
    inside_ring,
    merge_points,
    neighbour_planes,
    outline,
    plane_basis,
    signed_area,
    snapped,
)
from .noise import fitted_normals, flat_only, kept_planes, noise_level

# A scan (``noise.noise_level`` reads its noise): its planes hold the points within NOISE_SIGMAS noise levels
# (3.5: all but 0.05 % of Gaussian noise), seeded by normals within NOISY_DEGREES, explaining all but NOISY_INLIERS
# of them (a dense scan's samples between its noisy vertices spread by less than the vertices do, so a few near the
# vertices lie beyond the noise read from the samples), and each plane's points lie off it by at most
# ``noise.FLAT_RMS`` noise levels in RMS.
NOISE_SIGMAS = 3.5
NOISY_DEGREES = 15.0
NOISY_INLIERS = 0.99
# A plane grown on a scan takes every free point within its tolerance whose fitted normal is not square to it
# (``PlanarConfig.loose_degrees``), so a panel set into a frame takes a strip of each wall it cuts across.  Each point
# then goes to the nearest plane holding it whose normal its fitted normal lies within HOLD_DEGREES of
# (``_by_normal``): fitted normals tilt by up to 45 degrees within a few points of an edge; a wall's lie 90 off.
HOLD_DEGREES = 45.0


@dataclass(frozen=True)
class PlanarConfig:
    """Tolerances of :func:`polyhedron`, in the unit frame (the input's longest side 1) or in point spacings."""

    tolerance: float = 2e-4  # a point lies on a plane within this distance (exact data: float32 rounding)
    normal_degrees: float = 5.0  # ... and with its normal this close to the plane's
    # ... or, once the plane is fitted, this close: normals estimated from a point's neighbours (a cloud without
    # normals) tilt by up to 45 degrees within a few points of an edge, though the points lie on their planes.
    loose_degrees: float = 89.0
    min_points: int = 12  # points a plane needs
    inliers: float = 0.998  # share of the points the planes must explain
    max_planes: int = 40
    max_seeds: int = 60  # seed points that found no plane before the input is called curved
    reach: float = 1.5  # cover and neighbour radius, in point spacings (median distance to the 8th neighbour)
    max_vertices: int = 256
    max_points: int = 20_000  # points read (a larger cloud is subsampled, fixed seed)


def polyhedron(points: np.ndarray, normals: np.ndarray, cfg: PlanarConfig = PlanarConfig()
               ) -> tuple[np.ndarray, np.ndarray] | None:
    """The closed polyhedron the planes of an oriented point cloud bound, or None where it is not one.

    Parameters
    ----------
    points : (N, 3) float, in the unit frame (``shape.Normalization``)
    normals : (N, 3) float, unit, pointing out of the shape (their sign orients the faces)
    cfg : tolerances

    Returns
    -------
    (V, 3) float64 vertices and (F, 3) int64 faces, closed, edge-manifold and consistently oriented, whose
    surface and the points are within ``cfg.reach`` spacings of each other both ways; or None.
    """
    made = planar_mesh(points, normals, cfg)
    if made is None:
        return None
    vertices, faces, pts, reach, _, _ = made
    return (vertices, faces) if _closed(faces) and _explains(vertices, faces, pts, reach) else None


def planar_mesh(points: np.ndarray, normals: np.ndarray, cfg: PlanarConfig, cut: Callable | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, np.ndarray, float] | None:
    """The faces the planes of an oriented point cloud make, each plane's cut by its neighbours' lines (and by the
    planes ``cut`` adds), before any check of the whole: what :func:`polyhedron` and ``open_planar`` share.

    ``cut(points, planes, labels, near, reach, tolerance)`` returns (S, 4) more planes, without points, and for
    each plane of ``planes`` the indices of those that end its faces; or (None, None) where there are none.
    Returns the vertices, faces, the points read (subsampled), the cover radius, the added planes and the plane
    tolerance at the points' noise (``cfg``'s, or wider for a scan); or None where a plane has no faces it can
    close, or the corners are too many."""
    found = planes_found(points, normals, cfg)
    if found is None:
        return None
    pts, _, planes, labels, cfg, spacing = found
    reach = cfg.reach * spacing
    near, real, extra = neighbour_planes(pts, labels, planes, reach, cfg.tolerance), len(planes), np.zeros((0, 4))
    if cut is not None:
        extra, ends = cut(pts, planes, labels, near, reach, cfg.tolerance)
        if extra is None:
            return None
        near = [mine | dict.fromkeys((real + j for j in end), 0) for mine, end in zip(near, ends, strict=True)]
        planes = np.vstack([planes, extra])
    corners, meets, loops = [], [], []
    for k in range(real):
        faces = plane_faces(k, planes, near[k], pts[labels == k], spacing, reach)
        if faces is None:
            return None
        for ring, lines in faces:
            loops.append((k, [len(corners) + i for i in range(len(ring))]))
            corners.extend(ring)
            meets.extend(np.c_[np.full(len(lines), k), lines])
    if not corners or len(corners) > 8 * cfg.max_vertices:
        return None
    # A corner on a line placed where the points stop is sure only to a fraction of a cover radius: near a corner
    # of the same two planes it is that corner.  Planes fitted to samples cross a little apart where many meet (a
    # cone's apex): corners within the plane tolerance are one vertex.
    corners = snapped(np.array(corners), np.array(meets), real, PLACED_SNAP * reach)
    vertices, index = merge_points(corners, cfg.tolerance)
    if len(vertices) > cfg.max_vertices:
        return None
    faces = _triangulate(vertices, planes, [(k, _distinct(index[ring])) for k, ring in loops], cfg.tolerance)
    return None if faces is None else (vertices, faces, pts, reach, extra, cfg.tolerance)


def planes_found(points: np.ndarray, normals: np.ndarray, cfg: PlanarConfig) -> tuple | None:
    """The planes of points (P, 3) with normals (P, 3) at their own noise: the points read and their normals, the
    (K, 4) planes, each point's plane (-1: none), the config at that noise, the median spacing; or None."""
    pts, nrm = _subsample(np.asarray(points, np.float64), np.asarray(normals, np.float64), cfg.max_points)
    found = _planes_at_noise(pts, nrm, cfg)
    if found is None:
        return None
    planes, labels, cfg = found
    spacing = float(np.median(cKDTree(pts).query(pts, k=9)[0][:, -1]))
    return pts, nrm, planes, labels, cfg, spacing


def _planes_at_noise(points: np.ndarray, normals: np.ndarray, cfg: PlanarConfig
                     ) -> tuple[np.ndarray, np.ndarray, PlanarConfig] | None:
    """:func:`detect_planes` at the points' own noise: the planes, the plane of each point, and the tolerances
    they were found with (``cfg``'s, or for a scan whose noise exceeds them those of ``NOISE_SIGMAS`` noise
    levels, its normals fitted to its neighbours, planes grown at an edge dropped (:func:`_regrown`), each point on
    the plane its fitted normal agrees with (``HOLD_DEGREES``), only the planes as flat as the noise: ``flat_only``)."""
    sigma = noise_level(points, normals)
    if NOISE_SIGMAS * sigma <= cfg.tolerance:
        found = detect_planes(points, normals, cfg)
        return None if found is None else (found[0], _by_normal(points, normals, *found, cfg), cfg)
    cfg = replace(cfg, tolerance=NOISE_SIGMAS * sigma, normal_degrees=NOISY_DEGREES, inliers=NOISY_INLIERS)
    fitted, order = fitted_normals(points, normals)
    found = detect_planes(points, fitted, cfg, order)
    if found is None:
        return None
    planes, labels = _regrown(points, fitted, *found, cfg)
    labels = _by_normal(points, fitted, planes, labels, replace(cfg, normal_degrees=HOLD_DEGREES))
    found = flat_only(points, planes, labels, sigma, cfg.inliers)
    return None if found is None else (*found, cfg)


def _regrown(points: np.ndarray, normals: np.ndarray, planes: np.ndarray, labels: np.ndarray, cfg: PlanarConfig
             ) -> tuple[np.ndarray, np.ndarray]:
    """``planes`` (K, 4) and ``labels`` (N,) without the planes that, grown again largest first over the points
    (as :func:`detect_planes` grows them), gather under ``cfg.min_points`` and whose points go more to planes
    across them than to planes along them; their points go to the plane that takes them then.  A scan's points near
    an edge have fitted normals turned toward the other side: seeded there before a short board's own points, a
    plane parallel to a wall and a tolerance or two off it takes the strip between them, and the board's points
    it shares with the wall then (``_by_normal``).  A plane whose points a parallel one takes is that sheet's own
    spread (a dense scan's samples lie wider than the noise read from them): it stays."""
    cos = (np.cos(np.radians(cfg.normal_degrees)), np.cos(np.radians(cfg.loose_degrees)))
    again = np.full(len(points), -1)
    for k in np.argsort(-np.bincount(labels[labels >= 0], minlength=len(planes)), kind="stable"):
        grown = _grow(points, normals, again < 0, planes[k, :3], planes[k, 3], cfg.tolerance, cos)
        if grown is not None and grown[1].sum() >= cfg.min_points:
            again[grown[1]] = k
    mine = labels >= 0
    along = np.abs(np.einsum("ij,ij->i", planes[labels[mine], :3], planes[again[mine], :3])) > cos[0]
    taken = again[mine] >= 0
    kept = np.isin(np.arange(len(planes)), again) | (
        np.bincount(labels[mine], taken & along, len(planes)) >= np.bincount(labels[mine], taken & ~along, len(planes)))
    return kept_planes(planes, np.where(kept[np.maximum(labels, 0)], labels, np.where(mine, again, -1)), kept)


def _distinct(ring: np.ndarray) -> np.ndarray:
    """A ring of vertex ids without repeats in a row (corners that merged into one vertex, as at a cone's
    apex, where several lines cross within rounding of each other)."""
    return ring[ring != np.roll(ring, 1)] if len(ring) > 1 else ring


def _subsample(points: np.ndarray, normals: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    if len(points) <= n:
        return points, normals
    keep = np.sort(np.random.default_rng(0).choice(len(points), n, replace=False))
    return points[keep], normals[keep]


def detect_planes(points: np.ndarray, normals: np.ndarray, cfg: PlanarConfig, order: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray] | None:
    """(N, 3) points and normals -> (K, 4) planes (unit normal n, offset d: n.x = d, n along the points'
    normals) and (N,) the plane of each point, or None where planes leave more than ``1 - cfg.inliers`` of the
    points unexplained.  Greedy: each unexplained point in turn (in the points' order, or ``order`` (N,)) seeds a
    plane from its own normal, refitted to the points it gathers."""
    cos = (np.cos(np.radians(cfg.normal_degrees)), np.cos(np.radians(cfg.loose_degrees)))
    labels = np.full(len(points), -1)
    planes, failed = [], 0
    allowed = len(points) * (1 - cfg.inliers)
    for seed in range(len(points)) if order is None else order:
        if (labels < 0).sum() <= allowed:
            break
        if labels[seed] >= 0:
            continue
        plane = _grow(points, normals, labels < 0, normals[seed], points[seed] @ normals[seed], cfg.tolerance, cos)
        if plane is None or len(planes) == cfg.max_planes:
            failed += 1
            if failed > cfg.max_seeds or len(planes) == cfg.max_planes:
                return None
            continue
        (n, d), members = plane
        if (members.sum()) < cfg.min_points:
            failed += 1
            if failed > cfg.max_seeds:
                return None
            continue
        labels[members] = len(planes)
        planes.append(np.r_[n, d])
    if (labels < 0).sum() > allowed or not planes:
        return None
    return np.array(planes), labels


def _by_normal(points: np.ndarray, normals: np.ndarray, planes: np.ndarray, labels: np.ndarray, cfg: PlanarConfig
               ) -> np.ndarray:
    """(N,) ``labels`` with each point on the nearest of ``planes`` (K, 4) that hold it (within ``cfg.tolerance``)
    and whose normal it shares (within ``cfg.normal_degrees``), where one does: a part whose face crosses a plane's
    extension elsewhere, its points along that line taken by the plane grown first, keeps them; of two halves of a
    quad folded a degree or two, each keeps its points in the strip along the fold that both hold (a third of a
    cover radius wide at 1.5 degrees), so that their faces meet on their line."""
    agree = np.abs(normals @ planes[:, :3].T) > np.cos(np.radians(cfg.normal_degrees))  # (N, K)
    off = np.abs(points @ planes[:, :3].T - planes[:, 3])
    held = agree & (off < cfg.tolerance)
    move = np.nonzero((labels >= 0) & held.any(1))[0]
    out = labels.copy()
    out[move] = np.where(held[move], off[move], np.inf).argmin(1)
    return out


def _grow(points, normals, free, n, d, tol, cos):
    """The plane a seed (normal ``n``, offset ``d``) grows to among the ``free`` points: its members (normals
    within ``cos[0]``) refitted by least squares twice, then every free point on it with its normal within
    ``cos[1]``.  Returns ((n, d), member mask), or None when it gathers under three points."""
    for _ in range(2):
        members = free & (np.abs(points @ n - d) < tol) & (np.abs(normals @ n) > cos[0])
        if members.sum() < 3:
            return None
        mine = points[members]
        centre = mine.mean(0)
        fitted = np.linalg.svd(mine - centre, full_matrices=False)[2][-1]
        n = fitted if fitted @ normals[members].sum(0) >= 0 else -fitted
        d = float(n @ centre)
    members = free & (np.abs(points @ n - d) < tol) & (np.abs(normals @ n) > cos[1])
    return (n, d), members


def plane_faces(k: int, planes: np.ndarray, near: Collection[int], points: np.ndarray, spacing: float, reach: float
                ) -> list[tuple[np.ndarray, np.ndarray]] | None:
    """The outlines of plane ``k``'s faces as (L, 3) corner rings in 3D, each with (L, 2) the two planes of
    ``near`` whose lines meet at each corner: the boundary of the cells of the arrangement of the lines where plane
    k meets them that its own ``points`` cover (``chosen``; ``spacing``: the points' median distance to their 8th
    neighbour).  None where a face reaches the box around the points (no neighbour bounds it) or two boundaries
    touch at a corner."""
    n, d = planes[k, :3], planes[k, 3]
    basis = plane_basis(n)  # (3, 2): u x v = n, so counter-clockwise in 2D is outward in 3D
    flat = (points - n * d) @ basis
    margin = 0.2 + 4 * reach
    cells = [Cell.box(flat.min(0) - margin, flat.max(0) + margin)]
    for j in sorted(near):  # plane j's line on plane k: n_j . (n d + basis @ x) = d_j
        coef = planes[j, :3] @ basis
        scale = np.linalg.norm(coef)
        cells = [part for cell in cells for part in cell.split(j, coef / scale, (planes[j, 3] - d * planes[j, :3] @ n)
                                                                / scale)]
    rings = outline(cells, chosen(cells, flat, spacing))
    if rings is None:
        return None
    out = []
    for ring in rings:
        lines = [line for _, line in ring]
        if min(lines) < 0:  # an edge of the box around the points: no plane ends this face
            return None
        # A corner's 2D point is where two lines cross, so lifted it lies on plane k and both neighbours.
        turns = [i for i in range(len(ring)) if _turns(ring[i - 1][0], ring[i][0], ring[(i + 1) % len(ring)][0])]
        if len(turns) < 3:  # a ring without area (cells along one line)
            return None
        corners = np.array([ring[i][0] for i in turns])
        out.append((n * d + corners @ basis.T, np.array([[lines[i - 1], lines[i]] for i in turns])))
    return out


def _turns(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> bool:
    """Whether a 2D boundary a -> b -> c turns at b (b is no point along one straight edge)."""
    ab, bc = b - a, c - b
    return abs(ab[0] * bc[1] - ab[1] * bc[0]) > 1e-10 * np.linalg.norm(ab) * np.linalg.norm(bc)


def _triangulate(vertices: np.ndarray, planes: np.ndarray, loops: list[tuple[int, np.ndarray]], tol: float
                 ) -> np.ndarray | None:
    """Faces filling each plane's rings of ``vertices`` ids (outer counter-clockwise seen along the plane's
    normal, holes clockwise), with the vertices other planes put on a ring's edges (within ``tol``) inserted, so that
    neighbouring faces share every edge.  Triangles by ear clipping (``mapbox_earcut``)."""
    import mapbox_earcut

    faces = []
    for k in sorted({k for k, _ in loops}):
        n = planes[k, :3]
        basis = plane_basis(n)
        rings = [_with_points_on_edges(vertices, ring, tol) for kk, ring in loops if kk == k]
        flat = [vertices[r] @ basis for r in rings]
        areas = [signed_area(f) for f in flat]
        outers = [i for i, a in enumerate(areas) if a > 0]
        for o in outers:
            members = [o] + [h for h, a in enumerate(areas) if a < 0 and inside_ring(flat[h][0], flat[o])]
            coords = np.vstack([flat[i] for i in members])
            ends = np.cumsum([len(flat[i]) for i in members]).astype(np.uint32)
            tri = _split_needles(mapbox_earcut.triangulate_float64(coords, ends).reshape(-1, 3), coords)
            ids = np.concatenate([rings[i] for i in members])[tri]
            normal = np.cross(vertices[ids[:, 1]] - vertices[ids[:, 0]], vertices[ids[:, 2]] - vertices[ids[:, 0]])
            flip = normal @ n < 0
            ids[flip] = ids[flip][:, ::-1]
            faces.append(ids)
        if sum(len(f) for f in flat if signed_area(f) < 0) and len(outers) == 0:
            return None
    return np.vstack(faces).astype(np.int64) if faces else None


def _split_needles(tri: np.ndarray, flat: np.ndarray) -> np.ndarray:
    """``tri`` (T, 3) ear-clipped triangles of 2D points ``flat`` (N, 2) with each needle (corners in a line: a
    ring's corner on a straight edge clipped as an ear of no area) dropped and the triangle across its long edge
    split at its middle corner instead, so that the corner's two edges each have their one triangle."""
    tri = [tuple(int(i) for i in t) for t in tri]
    scale = max(float(np.ptp(flat, axis=0).max()) ** 2, 1e-300)
    for _ in range(len(tri)):
        t = flat[np.array(tri)]
        e1, e2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
        area = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
        bad = np.flatnonzero(np.abs(area) <= 1e-12 * scale)
        if not len(bad):
            break
        a, b, c = tri[bad[0]]
        p, q, m = max(((a, b, c), (b, c, a), (c, a, b)), key=lambda e: np.linalg.norm(flat[e[1]] - flat[e[0]]))
        across = [j for j, u in enumerate(tri) if (q, p) in ((u[0], u[1]), (u[1], u[2]), (u[2], u[0]))]
        if not across:
            break
        u = tri[across[0]]
        x = next(i for i in u if i not in (p, q))
        tri = [u2 for j, u2 in enumerate(tri) if j not in (bad[0], across[0])] + [(q, m, x), (m, p, x)]
    return np.array(tri, dtype=np.int64).reshape(-1, 3)


def _with_points_on_edges(vertices: np.ndarray, ring: np.ndarray, tol: float) -> np.ndarray:
    """``ring`` of vertex ids with every other vertex inside one of its edges (within ``tol``) inserted in order."""
    out = []
    for a, b in zip(ring, np.roll(ring, -1), strict=True):
        out.append(a)
        ab = vertices[b] - vertices[a]
        t = (vertices - vertices[a]) @ ab / max(ab @ ab, 1e-30)
        off = np.linalg.norm(vertices - vertices[a] - t[:, None] * ab, axis=1)
        inside = np.nonzero((t > 1e-6) & (t < 1 - 1e-6) & (off < tol))[0]
        out.extend(inside[np.argsort(t[inside])])
    return np.array(out, dtype=np.int64)


def _closed(faces: np.ndarray) -> bool:
    """Whether every edge has two faces, one each way (closed, edge-manifold and consistently oriented)."""
    e = np.c_[faces.ravel(), faces[:, [1, 2, 0]].ravel()]
    if len(np.unique(e, axis=0)) != len(e):
        return False
    count = np.unique(np.sort(e, axis=1), axis=0, return_counts=True)[1]
    return bool((count == 2).all())


def _explains(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, reach: float) -> bool:
    """Whether the surface and the points lie within twice ``reach`` of each other both ways (at the points'
    own sampling density)."""
    from .io import sample_triangles

    area = np.linalg.norm(np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]],
                                   vertices[faces[:, 2]] - vertices[faces[:, 0]]), axis=1)
    if (area < 1e-12).any():
        return False
    samples = sample_triangles(vertices, faces, len(points), np.random.default_rng(0))[0]
    there = cKDTree(points).query(samples)[0].max()
    back = cKDTree(samples).query(points)[0].max()
    return bool(max(there, back) < 2 * reach)
