"""Piecewise-planar shapes of any arrangement (insets, bays, steps, notches, bevels) rebuilt from their planes: the
input's box split by its planes into convex cells, each labelled inside or outside by a minimum cut, their union
the mesh.

:func:`.planar.polyhedron` cuts each plane's faces from the lines of its neighbours, which closes boxes, pockets,
notches and chamfers, but not a plane whose faces face both ways (two boxes stacked off-centre: the upper one's
overhang faces down in the plane of the lower one's top) or a face no neighbour's line bounds (a table's top, its
legs standing on it). Here, as in PolyFit (Nan and Wonka, 2017) and Kinetic Shape Reconstruction (Bauchet and
Lafarge, 2020), the planes cut space instead: the input's box, grown, is split by each plane (largest first) only in
the cells its own points reach (:func:`.plane_arrangement.plane_arrangement`), which keeps the cells few. Each cell
costs its volume times how far the input's generalized winding number there is from the label
(``winding.winding_numbers``), each facet between two cells the part of its area its plane's points do not cover
(:func:`.plane_arrangement.facets`); the least-cost labelling is a minimum cut (``cells.min_cut``, the face
stage's) (:func:`labelled`); a cell whose winding number says it is part inside, part out (a step whose small
face holds too few points for a plane, so that no plane stops there) is first split by every plane crossing it
(:func:`.plane_arrangement.refined`). The facets between inside and outside cells are the surface: exact where
cells meet (their corners come from the same planes), closed once the corners other facets put on an edge are inserted
(:func:`_fans`), each flat region then triangulated from its outline (``kitbash.flat_rebuild``, as a kitbashed union
is) (:func:`cells_surface`); kept only where it and the input lie within the planes path's tolerance of each other
both ways (:func:`plane_cells`).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull, cKDTree

from ..shapes.arrangement import merge_points, plane_basis, signed_area
from ..shapes.planar import PlanarConfig, _closed, _distinct, _with_points_on_edges, planes_found
from .cells import min_cut
from .kitbash import flat_rebuild, flat_regions
from .meshops import distance_to_triangles, remove_unreferenced, wound_alike
from .plane_arrangement import GROWN, WELD_EPS, Polytope, facets, plane_arrangement, polygon_area, refined
from .winding import winding_numbers

MAX_REGIONS = 256  # flat regions of the union (``kitbash.MAX_REGIONS``)
# A facet uncovered by its plane's points costs its area times SMOOTH_SPACINGS point spacings, against a cell's
# volume: a slab thinner than that between the input's planes goes with its neighbours, whatever its winding.
SMOOTH_SPACINGS = 2.0
# Every point lies within this many plane tolerances (at the points' noise: ``planar.NOISE_SIGMAS`` of it) of the
# rebuild: on random flat shapes scanned with 0.3 % noise the right rebuilds lie within 1.1-1.4 of them of their
# points, the boxes that left out a bevel's chamfers 3-4 (4.5-6 % of the size off the truth).  The surface's own
# samples need only lie within twice the reach of a point: the points do not cover it evenly.
COVER_TOLERANCES = 2.0
# A cell whose winding number lies within MIXED of a half is part inside, part out (a step whose small face has no
# plane of its own left it whole): it is split by every plane that crosses it before the labelling.  On random
# kitbashed props as points of their outside, 14 -> 21 of 48 rebuilt exactly (the benchmark's 32: no change).
MIXED = 0.3


def cell_windings(cells: list[Polytope], points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(C,) the input's winding number (``points``, ``normals`` (N, 3)) in each cell, clipped to [0, 1]: the mean
    at its centroid and halfway to its corners."""
    corners = [c.corners() for c in cells]
    queries = np.vstack([np.vstack([c.mean(0), 0.5 * (c + c.mean(0))]) for c in corners])
    w = np.clip(winding_numbers(queries, points, normals), 0.0, 1.0)
    start = np.r_[0, np.cumsum([len(c) + 1 for c in corners])]
    return np.add.reduceat(w, start[:-1]) / np.diff(start)


def labelled(cells: list[Polytope], w: np.ndarray, a: np.ndarray, b: np.ndarray, cost: np.ndarray) -> np.ndarray:
    """(C,) bool, the cells inside: the least-cost labelling (``cells.min_cut``), each cell costing its volume
    times the share of its winding number ``w`` (C,) (:func:`cell_windings`) against the label, each facet between
    cells ``a`` and ``b`` (T,) ``cost`` (T,) where they are labelled apart."""
    volume = np.array([ConvexHull(c.corners()).volume for c in cells])
    return min_cut(len(cells), volume * (1 - w), volume * w, a, b, cost)


def cells_surface(planes: np.ndarray, pid: np.ndarray, rings: list[np.ndarray], a: np.ndarray, b: np.ndarray,
                  inside: np.ndarray, tol: float, open_: bool = False) -> tuple[np.ndarray, np.ndarray] | None:
    """The boundary of the inside cells: the facets between an inside and an outside cell, each wound outward,
    their corners made one where they meet and each flat region triangulated again from its outline
    (``kitbash.flat_rebuild``).

    Parameters
    ----------
    planes : (K + 6, 4) float, the planes the facets lie on
    pid : (T,) int, each facet's plane; rings : T (m, 2) counter-clockwise rings in its plane
        (``shapes.arrangement.plane_basis``)
    a, b : (T,) int, the cells below and beyond each facet's plane (-1: outside the box)
    inside : (C,) bool
    tol : float, corners this close are one vertex: planes fitted to samples cross a little apart where more than
        three meet (``planar.planar_mesh`` merges its corners within its plane tolerance, as here)
    open_ : bool, an inside cell may touch the box: the facets on the box are left out, and the surface is open
        there (a building without its floor)

    Returns
    -------
    (V, 3) float64 vertices and (F, 3) int64 faces, closed (or with ``open_`` open only on the box) and oriented
    outward; or None where they are not (a cell in the box's edge labelled inside), or the union has more than
    ``MAX_REGIONS`` flat regions.
    """
    made = _outward_facets(planes, pid, rings, a, b, inside, open_)
    if made is None:
        return None
    corners, loops, oriented, row_plane = made
    # Merged within ``tol`` first (corners where more than three planes meet are one vertex), else only within
    # rounding where that merges a small facet's corners across it (a noisy scan's ``tol`` is 3.5 noise levels).
    made = _welded(corners, oriented, loops, tol, open_) or _welded(corners, oriented, loops, WELD_EPS, open_)
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
    # Where the outlines do not triangulate into a closed mesh the fans stand: closed and exact, only more faces.
    return (vertices, faces) if rebuilt is None or len(rebuilt[1]) > len(faces) else rebuilt


def _outward_facets(planes: np.ndarray, pid: np.ndarray, rings: list[np.ndarray], a: np.ndarray, b: np.ndarray,
                    inside: np.ndarray, open_: bool = False) -> tuple[np.ndarray, list, np.ndarray, np.ndarray] | None:
    """The facets between an inside and an outside cell (:func:`cells_surface`'s parameters) in 3D, each wound
    outward: (C, 3) their corners, their rings (plane row, (m,) ids into the corners), (P, 4) the rows: each
    plane facing one way, and (P,) the plane of each row.  None where there are none or an inside cell touches the
    box (with ``open_``, that facet is left out)."""
    ins_a = inside[a]
    ins_b = np.where(b < 0, False, inside[np.maximum(b, 0)])
    corners, loops, rows = [], [], {}
    for t in np.flatnonzero(ins_a != ins_b):
        if b[t] < 0:
            if open_:
                continue
            return None
        sign = 1.0 if ins_a[t] else -1.0
        n, d = planes[pid[t], :3], planes[pid[t], 3]
        ring = n * d + rings[t] @ plane_basis(n).T
        if signed_area(ring @ plane_basis(sign * n)) < 0:
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


def _welded(corners: np.ndarray, planes: np.ndarray, loops: list[tuple[int, np.ndarray]], tol: float,
            open_: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The facets' rings ``loops`` ((plane row, (m,) ids into ``corners`` (C, 3))) as one closed mesh: corners
    within ``tol`` made one vertex, each ring fanned with the vertices on its edges (:func:`_fans`, on
    ``planes`` (P, 4)): vertices, faces and the plane row of each face; None where that is not closed (with
    ``open_``: no edge in more than two faces) and consistently wound."""
    vertices, index = merge_points(corners, tol)
    rings = [(k, _distinct(index[ids])) for k, ids in loops]
    # A facet whose corners merged into a line (a sliver narrower than ``tol``) is none.
    rings = [(k, ring) for k, ring in rings if len(ring) >= 3 and polygon_area(
        vertices[ring] @ plane_basis(planes[k, :3])) > WELD_EPS * np.ptp(vertices[ring], axis=0).max()]
    if not rings:
        return None
    vertices, faces, row = _fans(vertices, planes, rings, tol)
    whole = _closed(faces) or (open_ and wound_alike(faces))
    return (*remove_unreferenced(vertices, faces)[:2], row) if whole else None


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


def plane_cells(points: np.ndarray, normals: np.ndarray, cfg: PlanarConfig = PlanarConfig(), open_: bool = False
                ) -> tuple[np.ndarray, np.ndarray] | None:
    """The closed mesh the planes of an oriented point cloud bound, whatever their arrangement; with ``open_`` the
    mesh open where the points stop on their box (a building without its floor, a crate without its lid).

    Parameters
    ----------
    points : (N, 3) float, in the unit frame (``shape.Normalization``)
    normals : (N, 3) float, unit, pointing out of the shape
    cfg : the planes path's tolerances (``planar.PlanarConfig``); its planes held at the points' own noise
    open_ : bool, the surface may stop on the box (``cells_surface``)

    Returns
    -------
    (V, 3) float64 vertices and (F, 3) int64 faces, closed (or open only on the box), edge-manifold and oriented
    outward, each flat region triangulated from its outline, on which every point lies within
    ``COVER_TOLERANCES`` plane tolerances (exact point-to-triangle distances) and whose samples lie within twice
    the planes path's reach (plus its plane tolerance) of a point; or None where the points are not held by planes,
    the cells are more than ``plane_arrangement.MAX_CELLS`` or the result is not that close.
    """
    found = planes_found(points, normals, cfg)
    if found is None:
        return None
    pts, nrm, planes, labels, cfg, spacing = found
    reach = cfg.reach * spacing
    made = plane_arrangement(pts, labels, planes, reach)
    if made is None:
        return None
    cells, all_planes = made
    w = cell_windings(cells, pts, nrm)
    mixed = np.abs(w - 0.5) < MIXED
    # (An open input's winding number is about a half along its sheets: its cells are not split for it.)
    finer = refined(cells, all_planes, len(planes), mixed) if mixed.any() and not open_ else None
    if finer is not None:
        cells, w = finer, cell_windings(finer, pts, nrm)
    a, b, pid, rings, uncovered = facets(cells, all_planes, len(planes), pts, labels, spacing)
    inside = labelled(cells, w, a, b, SMOOTH_SPACINGS * spacing * uncovered)
    if not inside.any():
        return None
    mesh = cells_surface(all_planes, pid, rings, a, b, inside, cfg.tolerance, open_)
    if mesh is None or not (_closed(mesh[1]) or open_):
        return None
    if not _closed(mesh[1]):
        mesh = _to_extent(*mesh, all_planes[len(planes):], cfg.tolerance)
    return mesh if _near(*mesh, pts, COVER_TOLERANCES * cfg.tolerance, 2 * reach + cfg.tolerance) else None


def _near(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, cover: float, limit: float) -> bool:
    """Whether the points lie within ``cover`` of the surface (exact distances) and the surface's samples (as many
    as the points) within ``limit`` of the points."""
    from ..shapes.io import sample_triangles

    if distance_to_triangles(points, vertices, faces).max() >= cover:
        return False
    samples = sample_triangles(vertices, faces, len(points), np.random.default_rng(0))[0]
    return bool(cKDTree(points).query(samples)[0].max() < limit)


def _to_extent(vertices: np.ndarray, faces: np.ndarray, box: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """An open surface's vertices on the cells' box (``box`` (6, 4), ``plane_arrangement.box_planes``: grown
    ``GROWN`` beyond the points) moved to where the points stop: each to the point of its faces' planes on its
    side of the points' own box, so that its walls end where theirs do."""
    region, planes = flat_regions(vertices, faces)
    v = vertices.copy()
    for side in box:
        on = np.flatnonzero(np.abs(vertices @ side[:3] - side[3]) < tol)
        for i in on:
            rows = planes[np.unique(region[(faces == i).any(axis=1)])]
            rows = rows[np.abs(rows[:, :3] @ side[:3]) < 1 - 1e-9]  # the walls through it, not the box's own plane
            lhs, rhs = np.vstack([rows[:, :3], side[:3]]), np.r_[rows[:, 3], side[3] - GROWN]
            v[i] += np.linalg.lstsq(lhs, rhs - lhs @ v[i], rcond=None)[0]  # the least move onto them all
    return v, faces
