"""Piecewise-planar shapes of any arrangement (insets, bays, steps, notches, bevels) rebuilt from their planes: the
input's box split by its planes into convex cells, each labelled inside or outside by a minimum cut, their union
the mesh.

:func:`.planar.polyhedron` cuts each plane's faces from the lines of its neighbours, which closes boxes, pockets,
notches and chamfers, but not a plane whose faces face both ways (two boxes stacked off-centre: the upper one's
overhang faces down in the plane of the lower one's top) or a face no neighbour's line bounds (a table's top, its
legs standing on it). Here, as in PolyFit (Nan and Wonka, 2017) and Kinetic Shape Reconstruction (Bauchet and
Lafarge, 2020), the planes cut space instead: the input's box, grown, is split by each plane (largest first) only in
the cells its own points reach (:func:`plane_arrangement`), which keeps the cells few. Each cell costs its volume
times how far the input's generalized winding number there is from the label (``winding.winding_numbers``), each
facet between two cells the part of its area its plane's points do not cover (:func:`facets`); the least-cost
labelling is a minimum cut (``solid.min_cut``, the face stage's). The facets between inside and outside cells are
the surface: exact where cells meet (their corners come from the same planes), closed once the corners other facets
put on an edge are inserted (:func:`_fans`), each flat region then triangulated from its outline
(``kitbash.flat_rebuild``, as a kitbashed union is) (:func:`cells_surface`); kept only where it and the input lie
within the planes path's tolerance of each other both ways (:func:`plane_cells`).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull, cKDTree

from ..shapes.arrangement import merge_points
from ..shapes.planar import PlanarConfig, _closed, _distinct, _planes_at_noise, _subsample, _with_points_on_edges
from .cells import min_cut
from .kitbash import flat_rebuild, flat_regions
from .meshops import distance_to_triangles, remove_unreferenced
from .winding import winding_numbers

MAX_CELLS = 4000  # an arrangement of more cells is refused: too many planes crossing to be a prop's flat parts
MAX_REGIONS = 256  # flat regions of the union (``kitbash.MAX_REGIONS``)
GROWN = 0.05  # the cells' box: the points' box grown by this (unit frame) on every side
WELD_EPS = 1e-8  # facets' corners this close are one: computed in different cells, they differ by ~1e-15
SPLIT_EPS = 1e-9  # a cell's corners within this of a plane lie on it (the plane does not cut the cell there)
MIN_SUPPORT = 3  # points of a plane within reach of a cell that make the plane cut it
# A facet uncovered by its plane's points costs its area times SMOOTH_SPACINGS point spacings, against a cell's
# volume: a slab thinner than that between the input's planes goes with its neighbours, whatever its winding.
SMOOTH_SPACINGS = 2.0
DENSITY = 7.67 / np.pi  # points per squared spacing (``arrangement.chosen``: a disc to the 8th neighbour holds 7.67)


class Polytope:
    """A convex cell: its faces, each (plane id, side, (m, 3) corner ring), ``side`` +1 where the cell lies on
    ``n . x <= d`` of the plane (its face's outward normal is the plane's) and -1 where beyond it."""

    def __init__(self, faces: list[tuple[int, int, np.ndarray]]):
        self.faces = faces

    def corners(self) -> np.ndarray:
        """(C, 3) the cell's distinct corners."""
        return merge_points(np.vstack([ring for _, _, ring in self.faces]), SPLIT_EPS)[0]

    def split(self, k: int, plane: np.ndarray) -> tuple[Polytope, Polytope] | None:
        """The parts of the cell below and beyond plane ``k`` ((4,): n, d), or None where it does not cut it."""
        n, d = plane[:3], plane[3]
        side = self.corners() @ n - d
        if side.min() > -SPLIT_EPS or side.max() < SPLIT_EPS:
            return None
        below, beyond, cut = [], [], []
        for pid, s, ring in self.faces:
            t = ring @ n - d
            t = np.where(np.abs(t) < SPLIT_EPS, 0.0, t)
            for sign, out in ((1.0, below), (-1.0, beyond)):
                part, crossings = _clipped(ring, sign * t)
                if part is not None:
                    out.append((pid, s, part))
                if sign > 0:
                    cut.extend(crossings)
        cap = _ring(np.array(cut), n)
        if cap is None or len(below) < 3 or len(beyond) < 3:
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
    basis = _basis(normal)
    flat = (points - points.mean(0)) @ basis
    return points[np.argsort(np.arctan2(flat[:, 1], flat[:, 0]))]


def _basis(normal: np.ndarray) -> np.ndarray:
    """(3, 2) two unit vectors spanning the plane of ``normal`` (u x v = normal)."""
    u = np.cross(normal, [1.0, 0, 0] if abs(normal[0]) < 0.9 else [0, 1.0, 0])
    u /= np.linalg.norm(u)
    return np.c_[u, np.cross(normal, u)]


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
    rings : T (m, 2) float, the facet, counter-clockwise in its plane's ``_basis``
    uncovered : (T,) float, the part of it that its plane's points do not cover: its area less as much area as
        its points stand for at their density; the box's faces wholly uncovered
    """
    a, b, pid, rings, uncovered = [], [], [], [], []
    per_plane: dict[int, list[tuple[int, int, np.ndarray]]] = {}
    for i, cell in enumerate(cells):
        for k, side, ring in cell.faces:
            per_plane.setdefault(k, []).append((i, side, ring))
    density = DENSITY / spacing**2
    for k, faces in per_plane.items():
        basis = _basis(planes[k, :3])
        flat = [(i, side, _ccw(ring @ basis)) for i, side, ring in faces]
        if k >= real:
            for i, _, f in flat:
                a.append(i), b.append(-1), pid.append(k), rings.append(f), uncovered.append(_area(f))
            continue
        mine = points[labels == k] @ basis
        beyond = [(j, f) for j, s, f in flat if s < 0]
        for i, f in ((i, f) for i, s, f in flat if s > 0):
            lo, hi = f.min(0), f.max(0)
            for j, g in beyond:
                if (g.min(0) >= hi).any() or (g.max(0) <= lo).any():
                    continue
                common = _convex_overlap(f, g)
                if common is not None:
                    a.append(i), b.append(j), pid.append(k), rings.append(common)
                    uncovered.append(max(_area(common) - _count_inside(mine, common) / density, 0.0))
    return (np.array(a, dtype=np.int64), np.array(b, dtype=np.int64), np.array(pid, dtype=np.int64), rings,
            np.array(uncovered))


def _area(flat: np.ndarray) -> float:
    x, y = flat.T
    return 0.5 * abs(float(x @ np.roll(y, -1) - y @ np.roll(x, -1)))


def _ccw(flat: np.ndarray) -> np.ndarray:
    x, y = flat.T
    return flat if float(x @ np.roll(y, -1) - y @ np.roll(x, -1)) >= 0 else flat[::-1]


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
    return out if _area(out) > WELD_EPS * np.ptp(out, axis=0).max() else None  # a sliver of rounding's width: none


def _count_inside(points: np.ndarray, ring: np.ndarray) -> int:
    """How many of the (P, 2) points lie inside the counter-clockwise convex ``ring`` (m, 2)."""
    if not len(points):
        return 0
    lo, hi = ring.min(0), ring.max(0)
    p = points[((points >= lo) & (points <= hi)).all(1)]
    edge = np.roll(ring, -1, axis=0) - ring
    rel = p[:, None, :] - ring[None]
    return int(((edge[None, :, 0] * rel[..., 1] - edge[None, :, 1] * rel[..., 0]) >= 0).all(1).sum())


def labelled(cells: list[Polytope], points: np.ndarray, normals: np.ndarray, a: np.ndarray, b: np.ndarray,
             cost: np.ndarray) -> np.ndarray:
    """(C,) bool, the cells inside: the least-cost labelling (``solid.min_cut``), each cell costing its volume
    times the share of the input's winding number (``points``, ``normals`` (N, 3); the mean at its centroid and
    halfway to its corners) against the label, each facet between cells ``a`` and ``b`` (T,) ``cost`` (T,) where
    they are labelled apart."""
    corners = [c.corners() for c in cells]
    volume = np.array([ConvexHull(c).volume for c in corners])
    queries = np.vstack([np.vstack([c.mean(0), 0.5 * (c + c.mean(0))]) for c in corners])
    w = np.clip(winding_numbers(queries, points, normals), 0.0, 1.0)
    start = np.r_[0, np.cumsum([len(c) + 1 for c in corners])]
    w = np.add.reduceat(w, start[:-1]) / np.diff(start)
    return min_cut(len(cells), volume * (1 - w), volume * w, a, b, cost)


def cells_surface(planes: np.ndarray, pid: np.ndarray, rings: list[np.ndarray], a: np.ndarray, b: np.ndarray,
                  inside: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray] | None:
    """The boundary of the inside cells: the facets between an inside and an outside cell, each wound outward,
    their corners made one where they meet and each flat region triangulated again from its outline
    (``kitbash.flat_rebuild``).

    Parameters
    ----------
    planes : (K + 6, 4) float, the planes the facets lie on
    pid : (T,) int, each facet's plane; rings : T (m, 2) counter-clockwise rings in its plane (``_basis``)
    a, b : (T,) int, the cells below and beyond each facet's plane (-1: outside the box)
    inside : (C,) bool
    tol : float, corners this close are one vertex: planes fitted to samples cross a little apart where more than
        three meet (``planar.planar_mesh`` merges its corners within its plane tolerance, as here)

    Returns
    -------
    (V, 3) float64 vertices and (F, 3) int64 faces, closed and oriented outward; or None where they are not (a
    cell in the box's edge labelled inside), or the union has more than ``MAX_REGIONS`` flat regions.
    """
    made = _outward_facets(planes, pid, rings, a, b, inside)
    if made is None:
        return None
    corners, loops, oriented, row_plane = made
    # Merged within ``tol`` first (corners where more than three planes meet are one vertex), else only within
    # rounding where that merges a small facet's corners across it (a noisy scan's ``tol`` is 3.5 noise levels).
    made = _welded(corners, oriented, loops, tol) or _welded(corners, oriented, loops, WELD_EPS)
    if made is None:
        return None
    vertices, faces, row = made
    # Corners merged within ``tol`` lie that far off their planes: moved the least onto them, so that each plane's
    # faces are one flat region (``kitbash.COPLANAR``), and a corner on a straight edge lies on its line (a plane's
    # faces facing both ways, as under a step's overhang, share its one offset).
    vertices = _onto(vertices, faces, row_plane[row], planes)
    found = flat_regions(vertices, faces, limit=MAX_REGIONS)
    if found is None:
        return None
    region, flat = found
    # Corners where more than three planes meet lie up to ``tol`` off some of them: an edge through one is straight
    # within that.
    rebuilt = flat_rebuild(vertices, faces, region, flat, straight=tol)
    return (vertices, faces) if rebuilt is None or len(rebuilt[1]) > len(faces) else rebuilt


def _outward_facets(planes: np.ndarray, pid: np.ndarray, rings: list[np.ndarray], a: np.ndarray, b: np.ndarray,
                    inside: np.ndarray) -> tuple[np.ndarray, list, np.ndarray, np.ndarray] | None:
    """The facets between an inside and an outside cell (:func:`cells_surface`'s parameters) in 3D, each wound
    outward: (C, 3) their corners, their rings (plane row, (m,) ids into the corners), (P, 4) the rows: each
    plane facing one way, and (P,) the plane of each row.  None where there are none or an inside cell touches the
    box."""
    ins_a = inside[a]
    ins_b = np.where(b < 0, False, inside[np.maximum(b, 0)])
    corners, loops, rows = [], [], {}
    for t in np.flatnonzero(ins_a != ins_b):
        if b[t] < 0:
            return None
        sign = 1.0 if ins_a[t] else -1.0
        n, d = planes[pid[t], :3], planes[pid[t], 3]
        ring = n * d + rings[t] @ _basis(n).T
        if _signed(ring @ _basis(sign * n)) < 0:
            ring = ring[::-1]
        key = (int(pid[t]), sign)
        rows.setdefault(key, len(rows))
        loops.append((rows[key], np.arange(len(corners), len(corners) + len(ring))))
        corners.extend(ring)
    if not loops:
        return None
    oriented, row_plane = np.zeros((len(rows), 4)), np.zeros(len(rows), dtype=np.int64)
    for (k, sign), row in rows.items():
        oriented[row], row_plane[row] = sign * planes[k], k
    return np.array(corners), loops, oriented, row_plane


def _welded(corners: np.ndarray, planes: np.ndarray, loops: list[tuple[int, np.ndarray]], tol: float
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The facets' rings ``loops`` ((plane row, (m,) ids into ``corners`` (C, 3))) as one closed mesh: corners
    within ``tol`` made one vertex, each ring fanned with the vertices on its edges (:func:`_fans`, on
    ``planes`` (P, 4)): vertices, faces and the plane row of each face; None where that is not closed and
    consistently wound."""
    vertices, index = merge_points(corners, tol)
    rings = [(k, _distinct(index[ids])) for k, ids in loops]
    # A facet whose corners merged into a line (a sliver narrower than ``tol``) is none.
    rings = [(k, ring) for k, ring in rings if len(ring) >= 3 and _area(vertices[ring] @ _basis(planes[k, :3]))
             > WELD_EPS * np.ptp(vertices[ring], axis=0).max()]
    if not rings:
        return None
    vertices, faces, row = _fans(vertices, planes, rings, tol)
    return (*remove_unreferenced(vertices, faces)[:2], row) if _closed(faces) else None


def _fans(vertices: np.ndarray, planes: np.ndarray, rings: list[tuple[int, np.ndarray]], tol: float
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each convex ring fanned from a vertex added at its centre, wound along its plane's normal, with the
    vertices that lie on its edges (within ``tol``: where the facets beside it end) in its fan, so that
    neighbouring facets share every edge.  A fan from the centre has no triangle without area, where ear clipping
    of a ring with corners in a line may (``kitbash.flat_rebuild`` then drops the centres).  Returns the vertices,
    the faces and (F,) the plane row of each."""
    out, centres = [], []
    for k, ring in rings:
        ring = _with_points_on_edges(vertices, ring, tol)
        centre = len(vertices) + len(centres)
        centres.append(vertices[ring].mean(0))
        tri = np.c_[np.full(len(ring), centre), ring, np.roll(ring, -1)]
        out.append((k, tri))
    vertices = np.vstack([vertices, centres])
    faces = []
    for k, tri in out:
        t = vertices[tri]
        if (np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]) @ planes[k, :3]).sum() < 0:
            tri = tri[:, [0, 2, 1]]
        faces.append(tri)
    return vertices, np.vstack(faces).astype(np.int64), np.concatenate([np.full(len(t), k) for k, t in out])


def _onto(vertices: np.ndarray, faces: np.ndarray, plane: np.ndarray, planes: np.ndarray) -> np.ndarray:
    """(V, 3) each vertex moved the least onto the planes (``planes`` (K, 4)) of its faces (``plane`` (F,)): exact
    where they meet in a point, a line or a plane, least squares where more than three miss each other."""
    pairs = np.unique(np.c_[faces.ravel(), np.repeat(plane, 3)], axis=0)  # each vertex's planes, once each
    at, n = pairs[:, 0], planes[pairs[:, 1], :3]
    miss = planes[pairs[:, 1], 3] - np.einsum("ij,ij->i", vertices[at], n)
    quad, rhs = np.zeros((len(vertices), 3, 3)), np.zeros((len(vertices), 3))
    np.add.at(quad, at, n[:, :, None] * n[:, None, :])
    np.add.at(rhs, at, n * miss[:, None])
    return vertices + np.einsum("nij,nj->ni", np.linalg.pinv(quad, rcond=1e-6, hermitian=True), rhs)


def _signed(flat: np.ndarray) -> float:
    x, y = flat.T
    return 0.5 * float(x @ np.roll(y, -1) - y @ np.roll(x, -1))


def plane_cells(points: np.ndarray, normals: np.ndarray, cfg: PlanarConfig = PlanarConfig()
                ) -> tuple[np.ndarray, np.ndarray] | None:
    """The closed mesh the planes of an oriented point cloud bound, whatever their arrangement.

    Parameters
    ----------
    points : (N, 3) float, in the unit frame (``shape.Normalization``)
    normals : (N, 3) float, unit, pointing out of the shape
    cfg : the planes path's tolerances (``planar.PlanarConfig``); its planes held at the points' own noise

    Returns
    -------
    (V, 3) float64 vertices and (F, 3) int64 faces, closed, edge-manifold and oriented outward, each flat region
    triangulated from its outline, whose surface and the points lie within twice the planes path's reach (plus
    its plane tolerance) of each other both ways (exact point-to-triangle distances one way, the surface's
    samples' nearest points the other); or None where the points are not held by planes, the cells are more than
    ``MAX_CELLS`` or the result is not that close.
    """
    pts, nrm = _subsample(np.asarray(points, np.float64), np.asarray(normals, np.float64), cfg.max_points)
    found = _planes_at_noise(pts, nrm, cfg)
    if found is None:
        return None
    planes, labels, cfg = found
    spacing = float(np.median(cKDTree(pts).query(pts, k=9)[0][:, -1]))
    reach = cfg.reach * spacing
    made = plane_arrangement(pts, labels, planes, reach)
    if made is None:
        return None
    cells, all_planes = made
    a, b, pid, rings, uncovered = facets(cells, all_planes, len(planes), pts, labels, spacing)
    inside = labelled(cells, pts, nrm, a, b, SMOOTH_SPACINGS * spacing * uncovered)
    if not inside.any():
        return None
    mesh = cells_surface(all_planes, pid, rings, a, b, inside, cfg.tolerance)
    if mesh is None or not _closed(mesh[1]):
        return None
    return mesh if _near(*mesh, pts, 2 * reach + cfg.tolerance) else None


def _near(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, limit: float) -> bool:
    """Whether the points lie within ``limit`` of the surface (exact distances) and the surface's samples (as many
    as the points) within ``limit`` of the points."""
    from ..shapes.io import sample_triangles

    if distance_to_triangles(points, vertices, faces).max() >= limit:
        return False
    samples = sample_triangles(vertices, faces, len(points), np.random.default_rng(0))[0]
    return bool(cKDTree(points).query(samples)[0].max() < limit)
