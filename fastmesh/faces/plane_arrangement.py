"""The arrangement of a piecewise-planar input's planes (:mod:`.plane_cells`'s first half): the input's box, grown,
split by each plane into convex cells, and the facets where two cells meet.

As in Kinetic Shape Reconstruction (Bauchet and Lafarge, 2020) a plane cuts only the cells its own points reach
(:func:`plane_arrangement`), which keeps the cells few: a plane stops where its points do.  Each cell is a
:class:`Polytope`, its faces convex rings on the planes that bound it; a cell is split by clipping each of its
faces (Sutherland-Hodgman) and capping both parts with the ring where the plane crosses it.  The facets between
cells (:func:`facets`) are the overlaps of a face of one cell with a face of another on the far side of the same
plane, each with the part of its area that its plane's points do not cover: what cutting through it costs the
labelling (``plane_cells.labelled``).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..shapes.arrangement import merge_points, plane_basis, signed_area

MAX_CELLS = 4000  # an arrangement of more cells is refused: too many planes crossing to be a prop's flat parts
GROWN = 0.05  # the cells' box: the points' box grown by this (unit frame) on every side
WELD_EPS = 1e-8  # facets' corners this close are one: computed in different cells, they differ by ~1e-15
SPLIT_EPS = 1e-9  # a cell's corners within this of a plane lie on it (the plane does not cut the cell there)
MIN_SUPPORT = 3  # points of a plane within reach of a cell that make the plane cut it
DENSITY = 7.67 / np.pi  # points per squared spacing (``arrangement.chosen``: a disc to the 8th neighbour holds 7.67)


class Polytope:
    """A convex cell: its faces, each (plane id, side, (m, 3) corner ring), ``side`` +1 where the cell lies on
    ``n . x <= d`` of the plane (its face's outward normal is the plane's) and -1 where beyond it."""

    def __init__(self, faces: list[tuple[int, int, np.ndarray]]):
        self.faces = faces
        self._corners: np.ndarray | None = None

    def corners(self) -> np.ndarray:
        """(C, 3) the cell's distinct corners, found once (every plane asks every cell whether its points reach it)."""
        if self._corners is None:
            self._corners = merge_points(np.vstack([ring for _, _, ring in self.faces]), SPLIT_EPS)[0]
        return self._corners

    def split(self, k: int, plane: np.ndarray) -> tuple[Polytope, Polytope] | None:
        """The parts of the cell below and beyond plane ``k`` ((4,): n, d), or None where it does not cut it."""
        n, d = plane[:3], plane[3]
        side = self.corners() @ n - d
        if side.min() > -SPLIT_EPS or side.max() < SPLIT_EPS:
            return None
        below, beyond, cut = [], [], []
        for pid, s, ring in self.faces:
            t = ring @ n - d
            t = np.where(np.abs(t) < SPLIT_EPS, 0.0, t)  # a corner on the plane is in both parts, not cut off
            for sign, out in ((1.0, below), (-1.0, beyond)):
                part, crossings = _clipped(ring, sign * t)
                if part is not None:
                    out.append((pid, s, part))
                if sign > 0:
                    cut.extend(crossings)
        cap = _ring(np.array(cut), n)
        if cap is None or len(below) < 3 or len(beyond) < 3:  # a part of no volume: the plane only grazes the cell
            return None
        return Polytope(below + [(k, 1, cap)]), Polytope(beyond + [(k, -1, cap)])


def _clipped(ring: np.ndarray, t: np.ndarray) -> tuple[np.ndarray | None, list[np.ndarray]]:
    """The part of a convex ``ring`` (m, 3) where ``t`` (m,) (signed distances of its corners) is not positive
    (Sutherland-Hodgman), None where it has no area; and the ring's points on ``t = 0`` (corners and crossings)."""
    out, on = [], []
    for i in range(len(ring)):
        j = (i + 1) % len(ring)
        if t[i] <= 0:
            out.append(ring[i])
        if t[i] == 0:
            on.append(ring[i])
        if t[i] * t[j] < 0:
            x = ring[i] + t[i] / (t[i] - t[j]) * (ring[j] - ring[i])
            out.append(x)
            on.append(x)
    if len(out) < 3:
        return None, on
    part = np.array(out)
    area = np.linalg.norm(np.cross(part[1:-1] - part[0], part[2:] - part[0]), axis=1).sum()
    return (part if area > SPLIT_EPS**2 else None), on


def _ring(points: np.ndarray, normal: np.ndarray) -> np.ndarray | None:
    """The distinct ``points`` (P, 3), lying in a plane of ``normal`` (3,), ordered around their centre as a convex
    ring; None where they are fewer than three."""
    if len(points) < 3:
        return None
    points = merge_points(points, SPLIT_EPS)[0]
    if len(points) < 3:
        return None
    flat = (points - points.mean(0)) @ plane_basis(normal)
    return points[np.argsort(np.arctan2(flat[:, 1], flat[:, 0]))]


def box_planes(points: np.ndarray) -> np.ndarray:
    """(6, 4) the planes of the points' box grown by ``GROWN``, normals pointing out."""
    lo, hi = points.min(0) - GROWN, points.max(0) + GROWN
    eye = np.eye(3)
    return np.array([np.r_[-eye[a], -lo[a]] for a in range(3)] + [np.r_[eye[a], hi[a]] for a in range(3)])


def _box_cell(box: np.ndarray, first: int) -> Polytope:
    """The box of ``box_planes`` as one cell, its faces numbered ``first`` .. ``first`` + 5."""
    lo, hi = -box[:3, 3], box[3:, 3]
    corner = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    faces = []
    for j, plane in enumerate(box):
        on = corner[np.abs(corner @ plane[:3] - plane[3]) < 1e-12]
        faces.append((first + j, 1, _ring(on, plane[:3])))
    return Polytope(faces)


def plane_arrangement(points: np.ndarray, labels: np.ndarray, planes: np.ndarray, reach: float
                      ) -> tuple[list[Polytope], np.ndarray] | None:
    """The input's box split into convex cells by its planes, each plane splitting only the cells that
    ``MIN_SUPPORT`` of its own points lie in or within ``reach`` of (Kinetic Shape Reconstruction's bound on the
    cells: a plane stops where its points do).

    Parameters
    ----------
    points : (N, 3) float, unit frame
    labels : (N,) int, the plane of each point (-1: none)
    planes : (K, 4) float, unit normals n and offsets d (n . x = d)
    reach : float, how far a point may lie outside a cell and still reach it

    Returns
    -------
    the cells, and (K + 6, 4) the planes their faces lie on (``planes``, then the box's); or None where the cells
    number more than ``MAX_CELLS``.
    """
    all_planes = np.vstack([planes, box_planes(points)])
    cells = [_box_cell(all_planes[len(planes):], len(planes))]
    # The largest planes first: they cut the box into its big parts before the small planes, which then reach
    # (and split) only the few cells near them.
    order = np.argsort(-np.bincount(labels[labels >= 0], minlength=len(planes)), kind="stable")
    for k in order:
        mine = points[labels == k]
        tree = cKDTree(mine)
        out = []
        for cell in cells:
            parts = cell.split(int(k), all_planes[k]) if _reached(cell, mine, tree, all_planes, reach) else None
            out.extend([cell] if parts is None else parts)
        cells = out
        if len(cells) > MAX_CELLS:
            return None
    return cells, all_planes


def refined(cells: list[Polytope], planes: np.ndarray, real: int, mixed: np.ndarray) -> list[Polytope] | None:
    """The cells with each ``mixed`` one (C,) bool split by every one of the first ``real`` planes that crosses it:
    a plane cuts only the cells its own points reach, so a small face whose plane was not found leaves a cell that
    runs on past a step in the surface, part inside and part out; the planes crossing it may split it there.
    None where the cells would then number more than ``MAX_CELLS``."""
    out = []
    for cell, split in zip(cells, mixed, strict=True):
        parts = [cell]
        for k in range(real) if split else ():
            parts = [q for part in parts for q in (part.split(k, planes[k]) or (part,))]
        out.extend(parts)
        if len(out) > MAX_CELLS:
            return None
    return out


def _reached(cell: Polytope, mine: np.ndarray, tree: cKDTree, planes: np.ndarray, reach: float) -> bool:
    """Whether ``MIN_SUPPORT`` of a plane's points ``mine`` (M, 3) lie in ``cell`` or within ``reach`` of it."""
    corners = cell.corners()
    centre = corners.mean(0)
    near = tree.query_ball_point(centre, float(np.linalg.norm(corners - centre, axis=1).max()) + reach)
    if len(near) < MIN_SUPPORT:
        return False
    ids = np.array([pid for pid, _, _ in cell.faces])
    sides = np.array([s for _, s, _ in cell.faces], dtype=float)
    off = (mine[near] @ planes[ids, :3].T - planes[ids, 3]) * sides
    return int((off <= reach).all(1).sum()) >= MIN_SUPPORT


def facets(cells: list[Polytope], planes: np.ndarray, real: int, points: np.ndarray, labels: np.ndarray,
           spacing: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[np.ndarray], np.ndarray]:
    """The facets between cells: where a face of one on a plane overlaps a face of another on its far side.

    Parameters
    ----------
    cells : the arrangement's (:func:`plane_arrangement`); planes : (K + 6, 4), its planes, the first ``real``
        the input's
    points : (N, 3) float, labels : (N,) int, the input's points and the plane of each (-1: none)
    spacing : float, the points' median distance to their 8th neighbour

    Returns
    -------
    a, b : (T,) int, the cells below and beyond the facet's plane (``b`` -1: outside the box, for its faces)
    pid : (T,) int, the facet's plane
    rings : T (m, 2) float, the facet, counter-clockwise in its plane's ``plane_basis``
    uncovered : (T,) float, the part of it that its plane's points do not cover: its area less as much area as
        its points stand for at their density; the box's faces wholly uncovered
    """
    found: list[tuple[int, int, int, np.ndarray, float]] = []  # (a, b, pid, ring, uncovered) of each facet
    density = DENSITY / spacing**2
    for k, faces in _faces_by_plane(cells).items():
        basis = plane_basis(planes[k, :3])
        flat = [(i, side, _ccw(ring @ basis)) for i, side, ring in faces]
        if k >= real:  # the box's: each face a facet on its own, with nothing beyond it
            found.extend((i, -1, k, f, polygon_area(f)) for i, _, f in flat)
        else:
            found.extend(_plane_facets(k, flat, points[labels == k] @ basis, density))
    a, b, pid, rings, uncovered = zip(*found, strict=True) if found else ((), (), (), (), ())
    return (np.array(a, dtype=np.int64), np.array(b, dtype=np.int64), np.array(pid, dtype=np.int64), list(rings),
            np.array(uncovered))


def _faces_by_plane(cells: list[Polytope]) -> dict[int, list[tuple[int, int, np.ndarray]]]:
    """The cells' faces grouped by their plane: plane id -> [(cell, side, (m, 3) ring)], in the cells' order."""
    per_plane: dict[int, list[tuple[int, int, np.ndarray]]] = {}
    for i, cell in enumerate(cells):
        for k, side, ring in cell.faces:
            per_plane.setdefault(k, []).append((i, side, ring))
    return per_plane


def _plane_facets(k: int, flat: list[tuple[int, int, np.ndarray]], mine: np.ndarray, density: float
                  ) -> list[tuple[int, int, int, np.ndarray, float]]:
    """The facets on the input's plane ``k``: each overlap of a face below it with one beyond it (``flat``: (cell,
    side, counter-clockwise (m, 2) ring) in the plane's basis), as (a, b, k, ring, uncovered area), the area the
    plane's points ``mine`` (M, 2) cover at ``density`` taken off."""
    out = []
    beyond = [(j, f) for j, s, f in flat if s < 0]
    if not beyond:
        return out
    low, high = np.array([g.min(0) for _, g in beyond]), np.array([g.max(0) for _, g in beyond])
    packed = _packed([g for _, g in beyond])
    for i, f in ((i, f) for i, s, f in flat if s > 0):
        near = np.nonzero(~((low >= f.max(0)).any(1) | (high <= f.min(0)).any(1)))[0]  # their boxes overlap
        if not len(near):
            continue
        for c in near[~_apart(f, *(a[near] for a in packed))]:
            j, g = beyond[c]
            common = _convex_overlap(f, g)
            if common is not None:
                covered = _count_inside(mine, common) / density
                out.append((i, j, k, common, max(polygon_area(common) - covered, 0.0)))
    return out


def _packed(rings: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rings (k, 2) of different lengths as (R, K, 2) corners, (R, K, 2) edges (each corner to the next) and
    (R, K) which of them are the ring's (the rest padding), for :func:`_apart`."""
    size = max(len(g) for g in rings)
    corners, edges = np.zeros((len(rings), size, 2)), np.zeros((len(rings), size, 2))
    valid = np.zeros((len(rings), size), dtype=bool)
    for r, g in enumerate(rings):
        corners[r, :len(g)], edges[r, :len(g)], valid[r, :len(g)] = g, np.roll(g, -1, axis=0) - g, True
    return corners, edges, valid


def _apart(f: np.ndarray, corners: np.ndarray, edges: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(R,) whether the counter-clockwise convex polygon ``f`` (m, 2) and each of R counter-clockwise convex rings
    (:func:`_packed`) lie on either side of an edge of one of them, touching at most: their overlap has no area and
    :func:`_convex_overlap` gives None, so it need not clip them (most pairs of a plane's faces whose boxes
    overlap).  The signed distances are :func:`_convex_overlap`'s own."""
    # f's corners against each ring's edges: (R, K, m), > 0 outside
    t = -(edges[..., :1] * (f[:, 1] - corners[..., 1:]) - edges[..., 1:] * (f[:, 0] - corners[..., :1]))
    beyond_ring = ((np.where(np.abs(t) < 1e-15, 0.0, t) >= 0).all(2) & valid).any(1)
    # each ring's corners against f's edges: (R, m, K)
    e = np.roll(f, -1, axis=0) - f
    t = -(e[:, :1] * (corners[:, None, :, 1] - f[:, 1:]) - e[:, 1:] * (corners[:, None, :, 0] - f[:, :1]))
    beyond_f = ((np.where(np.abs(t) < 1e-15, 0.0, t) >= 0) | ~valid[:, None, :]).all(2).any(1)
    return beyond_ring | beyond_f


def polygon_area(flat: np.ndarray) -> float:
    """The area of a polygon (m, 2), whichever way it winds."""
    return abs(signed_area(flat))


def _ccw(flat: np.ndarray) -> np.ndarray:
    """The polygon (m, 2) wound counter-clockwise."""
    return flat if signed_area(flat) >= 0 else flat[::-1]


def _convex_overlap(f: np.ndarray, g: np.ndarray) -> np.ndarray | None:
    """The intersection of two counter-clockwise convex polygons (m, 2) and (k, 2), or None where it is no wider
    than ``WELD_EPS``."""
    out = f
    for p, q in zip(g, np.roll(g, -1, axis=0), strict=True):
        e = q - p
        t = -(e[0] * (out[:, 1] - p[1]) - e[1] * (out[:, 0] - p[0]))  # > 0: right of the edge, outside
        t = np.where(np.abs(t) < 1e-15, 0.0, t)
        out = _clipped(np.c_[out, np.zeros(len(out))], t)[0]
        if out is None:
            return None
        out = out[:, :2]
    return out if polygon_area(out) > WELD_EPS * np.ptp(out, axis=0).max() else None  # a sliver of rounding's width


def _count_inside(points: np.ndarray, ring: np.ndarray) -> int:
    """How many of the (P, 2) points lie inside the counter-clockwise convex ``ring`` (m, 2)."""
    if not len(points):
        return 0
    lo, hi = ring.min(0), ring.max(0)
    p = points[((points >= lo) & (points <= hi)).all(1)]
    edge = np.roll(ring, -1, axis=0) - ring
    rel = p[:, None, :] - ring[None]
    return int(((edge[None, :, 0] * rel[..., 1] - edge[None, :, 1] * rel[..., 0]) >= 0).all(1).sum())
