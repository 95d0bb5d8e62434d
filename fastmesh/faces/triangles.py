"""The paper's face rule and its clean-up: triangles of mutually connected vertex triplets (:mod:`.cliques`),
then clean-up, and :class:`TriangleConfig`, the options of the whole face stage.

Not every 3-cycle is a face (three faces around a valence-3 vertex close a 3-cycle over its
ring, a flat quad with both diagonals gives four triangles), so :func:`fastmesh.faces.mesh_from_adjacency`
optionally drops zero-area triangles and one diagonal of coplanar 4-cliques (the variant in
the authors' release), keeps at most two faces per edge, then orients the faces consistently and outward
(:mod:`.orient`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..tokenizer.grid import CELL
from .cliques import cliques4
from .meshops import distinct_corners, triangle_areas


@dataclass
class TriangleConfig:
    """Options of :func:`mesh_from_adjacency`; the defaults are what ships (``weights/pipeline.json`` "faces").

    Attributes
    ----------
    selection : str
        ``"surface"``: restricted Delaunay triangles on the input surface, scored by the model,
        selected to stay a surface and holes filled (:func:`fastmesh.faces.surface_triangles.surface_mesh`,
        needs the input's samples; it reads ``support_points``, the ``"surface"`` options and
        ``remove_unreferenced``, and always orients).  ``"cliques"``: the paper's rule, the 3-cycles of the
        predicted edges with the clean-up options below (``fastmesh eval`` measures it beside the shipped one).
    drop_zero_area : bool
        ``"cliques"``: drop triangles whose area is at most ``area_tol * L**2`` (L = bounding-box
        longest side): collinear triplets are 3-cycles but not faces.
    area_tol : float
    drop_coplanar_diagonals : bool
        ``"cliques"``: for each 4-clique whose points lie within ``coplanar_tol * L`` of a plane: if it is
        a convex quad, drop its longer diagonal (every triangle using that edge); if one
        point lies inside the triangle of the other three, drop that outer triangle.
    coplanar_tol : float
        Default: half a 7-bit cell of the unit cube (quantisation moves points that much).
    orient : bool
        ``"cliques"``: make windings agree across edges shared by two faces, and each connected part face
        outward (positive signed volume about the mesh centroid).
    remove_unreferenced : bool
        Drop vertices no face uses (returned vertices are then a subset).
    support_tol : float or None
        ``"cliques"``, with the input's surface samples given: drop faces that stray farther than this
        from them (:func:`fastmesh.faces.support.supported`; relative to their longest side).
    support_points : int
        How many samples of the input surface to check against (a point cloud with fewer points
        gives all of them).
    max_faces_per_edge : int or None
        ``"cliques"``: keep faces best-supported first (with the input's samples; else in order) while
        no edge carries more than this many (:func:`limit_faces_per_edge`); 2 = edge-manifold.
    surface_tol : float or None
        ``"surface"``: the support limit relative to the points' longest side (None: only the
        floor of ``support.SPACING_FACTOR`` point spacings, which measures best).
    fold_angle : float
        ``"surface"``: degrees; two faces on an edge closer than this around it overlap.
    fill_max_loop : int
        ``"surface"``: longest boundary loop closed (``fastmesh.faces.holes.fill_holes``; 0 = no filling).
    model_weight : float
        ``"surface"``: weight of the mean log-probability of a triangle's edges in its score, against
        its support distance in units of the support limit (docs/results.md).
    close : bool
        ``"surface"``: close the loops hole filling left open (:func:`fastmesh.faces.closure.close_loops`): the
        pipeline sets it per request, for an input that is closed (``closure.decide_closed``).
    close_everywhere : bool
        ``close`` with no reach: every loop is closed, however far its cap lies from the input samples (the
        closure's last steps otherwise leave a loop open whose every cap strays beyond a few support limits:
        an opening of the input).  The pipeline sets it per request for a closed mesh input, which has none
        (``Request.sealed``).
    flat_tol : float or None
        Last, remove the vertices of flat regions, straight creases and straight open borders
        (:func:`fastmesh.faces.simplify.collapse_flat`): a kept vertex stays within ``flat_tol * L``
        of the faces it replaces (None: keep every vertex).  Default: half a 7-bit cell.  The pipeline
        turns it off for a face-count target told to the decoder (``SamplingConfig.read_count``).
    weigh_decimation : bool
        The pipeline, last: a mesh input's result is weighed against the input's quadric decimation to the same
        face count where that is as much an asset (``pipeline.result.decimated``), and the one nearer the input
        comes back.  ``Pipeline.random`` turns it off (its networks' meshes would never be the nearer).
    redistribute : float or None
        The pipeline, last: a point cloud's result is split to this many times its faces and simplified back
        (:func:`fastmesh.faces.redistribute.redistribute`), and comes back so where that lies nearer the input
        (``pipeline.result.redistributed``).  None: not tried.
    swap_edges : bool
        The pipeline: a generated result's edges turned where the other diagonal of their two triangles lies
        nearer the input and neither triangle then crosses another face (:func:`fastmesh.faces.swap.swap_edges`,
        ``uncrossed``), after its redistribution is weighed and before a mesh input's decimation is.
    refine : float or None
        The pipeline, after the decimation is weighed: a point cloud's generated result has its edges split where
        the input bends away from their middles by more than this (relative to the result's longest side)
        (:func:`fastmesh.faces.refine.refine`), kept where it lies nearer the input.  None: not split.
    add_missed : float or None
        The pipeline, once a frame's candidates are weighed: the input points farther than ``missed_tol`` from
        the chosen mesh, at most this many times its vertices (:func:`fastmesh.faces.missed.missed_points`), are
        added to its vertices and the face stage runs again; that mesh comes back where it lies nearer the input
        (``pipeline.candidate``).  None: not tried.
    missed_tol : float
        Relative to the unit cube the result is made in: the distance from the mesh at which an input point is
        missed, and the least spacing of the points added.
    quadric_vertices : bool
        The pipeline, once a frame's candidates are weighed and before ``add_missed``: a mesh input's chosen mesh
        is weighed against the face stage's mesh on the vertices of the input's quadric decimation to the same
        face count, and the one nearer the input is kept (``pipeline.candidate``).
    reach_extent : bool
        The pipeline, last: the box of a result that is not the input itself brought to the input's, where it
        falls short of a side by more than a quarter cell (:func:`fastmesh.faces.extent.reach_extent`).
    solid : float or None
        The pipeline, per candidate: the surface as the boundary of a solid (:func:`fastmesh.faces.solid.solid_mesh`:
        Delaunay cells of the vertices labelled inside or outside by a minimum cut of the input's winding numbers
        and the edge probabilities) comes back where its ``support.weighed_fit`` is at most this many times the
        surface selection's (``info.solid_fits``), for point-cloud inputs.  None: not made.  What ships keeps it
        within 1.1 times.
    solid_patch : bool
        With ``solid``: where the solid alone lies too far from the input, the selection's faces that carry a part
        of the input the cut lost (a wing or a boom the vertices cannot enclose) are added to it as pieces of their
        own (:func:`fastmesh.faces.solid.lost_parts`), and that is weighed instead.
    solid_open : bool
        With ``solid``: an open input (``close`` False) gets the solid stage too, cut as a closed input's: what it
        encloses comes back as a solid, the parts that enclose nothing (a wing, a sheet) patched in from the
        selection's mesh, then its faces across the input's openings taken off (:mod:`fastmesh.faces.uncapped`);
        else only a closed input does.
    outline : bool
        The pipeline, before ``reach_extent``: a generated result's flat regions triangulated from their outlines
        (:func:`fastmesh.faces.outline.outlined`), kept where no face then crosses another and it lies near the
        input as the result does (``pipeline.finish.FEWER_FACES_MARGIN``).  Not with a ``target_faces``.
    coarsen : float or None
        The pipeline, once the result is closed: a generated result's vertices collapsed while each stays within this
        distance (unit cube) of the planes it stands for and leaves no input sample a cell farther
        (:func:`fastmesh.pipeline.finish.coarsened`), kept where it adds no open, crowded or crossing edge and lies
        near the input as the result does.  None: not collapsed;
        not with a ``target_faces`` (brought to it instead).
    """

    selection: str = "surface"
    drop_zero_area: bool = True
    area_tol: float = 1e-10
    drop_coplanar_diagonals: bool = True
    coplanar_tol: float = 0.5 * CELL
    orient: bool = True
    remove_unreferenced: bool = True
    support_tol: float | None = 0.03
    support_points: int = 16384
    max_faces_per_edge: int | None = 2
    surface_tol: float | None = None
    fold_angle: float = 30.0
    fill_max_loop: int = 64
    model_weight: float = 0.1
    close: bool = False
    close_everywhere: bool = False
    flat_tol: float | None = 0.5 * CELL
    weigh_decimation: bool = True
    redistribute: float | None = 2.0
    swap_edges: bool = True
    refine: float | None = CELL
    add_missed: float | None = 0.5
    missed_tol: float = 0.01
    quadric_vertices: bool = True
    reach_extent: bool = True
    solid: float | None = 1.1
    solid_patch: bool = True
    solid_open: bool = True
    outline: bool = True
    coarsen: float | None = 0.25 * CELL

    def __post_init__(self):
        if self.selection not in ("cliques", "surface"):
            raise ValueError(f"selection must be 'cliques' or 'surface', got {self.selection!r}")


# --------------------------------------------------------------------------- clean-up


def _scale(vertices: np.ndarray) -> float:
    return float(np.ptp(vertices, axis=0).max()) if len(vertices) else 1.0


def drop_degenerate(vertices: np.ndarray, faces: np.ndarray, area_tol: float = 1e-10) -> np.ndarray:
    """Drop faces with a repeated index or an area at most ``area_tol * L**2``; then duplicates
    (the same vertex set, whatever the winding; the first one is kept)."""
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    ok = distinct_corners(f)
    f = f[ok]
    if len(f) == 0:
        return f
    f = f[triangle_areas(vertices, f) > area_tol * _scale(vertices) ** 2]
    _, first = np.unique(np.sort(f, axis=1), axis=0, return_index=True)
    return f[np.sort(first)]


def drop_coplanar_diagonals(vertices: np.ndarray, faces: np.ndarray, coplanar_tol: float = 0.5 * CELL,
                            cases: tuple[str, ...] = ("convex", "inner")) -> np.ndarray:
    """Resolve coplanar 4-cliques of the faces' edge graph (see ``TriangleConfig``).

    Parameters
    ----------
    vertices : (V, 3) float
    faces : (F, 3) int
        Triangles (typically all 3-cycles of a predicted adjacency).
    coplanar_tol : float
        Plane distance allowed, as a fraction of the bounding-box longest side.
    cases : tuple of str
        Which cliques to resolve: ``"convex"`` quads (drop the longer diagonal) and/or
        ``"inner"`` ones (a point inside the others' triangle: drop that outer triangle).
    """
    from .meshops import edges_from_faces

    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    v = np.asarray(vertices, dtype=np.float64)
    quads = cliques4(edges_from_faces(f), len(v))
    if len(quads) == 0:
        return f
    flat, cross, big = _clique_shapes(v, quads, coplanar_tol)
    convex = flat & (cross.sum(1) == 1) & ("convex" in cases)
    inner = flat & (cross.sum(1) == 0) & ("inner" in cases)
    drop_edges = np.zeros((0, 2), dtype=np.int64)
    if convex.any():
        kk = np.flatnonzero(convex)
        pi = cross[kk].argmax(1)
        pa, pb = quads[kk[:, None], _PAIRINGS[pi][:, :2]], quads[kk[:, None], _PAIRINGS[pi][:, 2:]]
        la = np.linalg.norm(v[pa[:, 0]] - v[pa[:, 1]], axis=1)
        lb = np.linalg.norm(v[pb[:, 0]] - v[pb[:, 1]], axis=1)
        drop_edges = np.sort(np.where((la >= lb)[:, None], pa, pb), axis=1)
    keep = np.ones(len(f), dtype=bool)
    n = len(v)
    if len(drop_edges):
        fe = np.sort(np.stack([f[:, [0, 1]], f[:, [1, 2]], f[:, [0, 2]]], axis=1), axis=2)  # (F, 3, 2)
        bad = np.isin(fe[..., 0] * n + fe[..., 1], drop_edges[:, 0] * n + drop_edges[:, 1])
        keep &= ~bad.any(1)
    if inner.any():
        kk = np.flatnonzero(inner)
        outer = np.sort(quads[kk[:, None], _OMIT[big[kk]]], axis=1)
        fs = np.sort(f, axis=1)
        keep &= ~np.isin((fs[:, 0] * n + fs[:, 1]) * n + fs[:, 2], (outer[:, 0] * n + outer[:, 1]) * n + outer[:, 2])
    return f[keep]


# The four triangles of a 4-clique: triangle t leaves out point t.
_OMIT = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])
# The pairings of four points into two segments; a flat convex quad's diagonals are the pairing that crosses.
_PAIRINGS = np.array([[0, 1, 2, 3], [0, 2, 1, 3], [0, 3, 1, 2]])


def _clique_shapes(v: np.ndarray, quads: np.ndarray, coplanar_tol: float
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Of each 4-clique ``quads`` (K, 4) of ``v``: (K,) whether it is flat (within ``coplanar_tol`` of the
    bounding box's longest side), (K, 3) which of the ``_PAIRINGS`` cross within its plane, and (K,) its
    largest triangle (of ``_OMIT``), whose plane it is measured in."""
    p = v[quads]  # (K, 4, 3)
    t = p[:, _OMIT]  # (K, 4, 3, 3)
    cr = np.cross(t[:, :, 1] - t[:, :, 0], t[:, :, 2] - t[:, :, 0])  # (K, 4, 3)
    area2 = np.linalg.norm(cr, axis=2)
    big = area2.argmax(1)  # most stable plane: the largest triangle
    k = np.arange(len(quads))
    normal = cr[k, big] / np.maximum(area2[k, big, None], 1e-300)
    dist = np.abs(((p[k, big] - t[k, big, 0]) * normal).sum(1))
    flat = (dist <= coplanar_tol * _scale(v)) & (area2[k, big] > 0)
    a, b, c, d = (p[:, _PAIRINGS[:, i]] for i in range(4))  # (K, 3, 3) each

    def side(o, e, x):  # sign of x relative to the line o-e, within the plane
        return (np.cross(e - o, x - o) * normal[:, None]).sum(-1)

    cross = (side(a, b, c) * side(a, b, d) < 0) & (side(c, d, a) * side(c, d, b) < 0)  # (K, 3)
    return flat, cross, big


def limit_faces_per_edge(faces: np.ndarray, score: np.ndarray, max_per_edge: int = 2) -> np.ndarray:
    """Keep faces best-first while none of their edges would carry more than ``max_per_edge`` faces.

    Parameters
    ----------
    faces : (F, 3) int
    score : (F,) float, lower is better (e.g. :func:`fastmesh.faces.support.support_distance`)
    max_per_edge : int
        2 makes every edge manifold: a triangle soup from dense cliques has interior and
        overlapping faces sharing edges, an artist mesh has at most two faces per edge.

    Returns
    -------
    (F', 3) int64 : the kept faces, in their original order.
    """
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(faces) == 0:
        return faces
    edges = np.sort(np.stack([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]], axis=1), axis=-1)  # (F, 3, 2)
    _, edge_id = np.unique(edges.reshape(-1, 2), axis=0, return_inverse=True)
    edge_id = edge_id.reshape(-1, 3)
    used = np.zeros(edge_id.max() + 1, dtype=np.int64)
    keep = np.zeros(len(faces), dtype=bool)
    for fi in np.argsort(score, kind="stable"):
        e = edge_id[fi]
        if (used[e] < max_per_edge).all():
            used[e] += 1
            keep[fi] = True
    return faces[keep]
