"""The face stage's surface as the boundary of a solid: Delaunay cells labelled inside or outside by a minimum cut.

The Delaunay tetrahedralisation of the decoded vertices and the corners of the input's grown box partitions that
box into cells; everything beyond it is one more cell, always outside.  Each cell is labelled inside or outside
by a global minimum cut (``cells.min_cut``) of

- a data term from the input (:func:`fastmesh.faces.winding.cell_winding`): the generalized winding number of its
  oriented samples (dipoles of the area each stands for, Barill et al. 2018) at points inside the cell; labelling
  a cell against it costs the area of its four triangles times how far the number lies from the threshold (the
  number read without its sign: an input wound inside-out reads -1 inside);
- a smoothness term from the face network (:func:`face_costs`): cutting through a triangle costs its area,
  little where the network says its three edges exist and much where it does not.

The surface returned is the interface between the two labels, each triangle wound from its inside cell to its
outside one (:func:`fastmesh.faces.labels.interface`).  Triangles of one tetrahedralisation never cross, so the
surface has no self-intersections and one consistent winding by construction, and it is closed: every edge bounds
an even number of its triangles.  Where the inside touches itself along an edge or at a vertex only, the cells
around that edge or vertex are relabelled (:func:`fastmesh.faces.labels.made_manifold`) until each edge has two
triangles and each vertex one fan.  :func:`solid_mesh` is the pipeline's entry, for closed and open inputs
alike: a part thinner than the vertices can enclose is cut again with the input's samples on it among the
vertices (``fastmesh.faces.thin``); where the solid lies farther from the input than the rival (the surface
selection's mesh), the parts the cut still loses (a wing, a sheet of an open input) come from the rival, made
thin closed parts united with the solid where the input lies on both their sides (``fastmesh.faces.slabs``), and
the rival comes back whole where even that lies farther.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .cells import cell_boundary_areas, cell_faces, min_cut, tetrahedralise
from .labels import interface, made_manifold
from .meshops import edge_face_counts, remove_unreferenced, triangle_areas, welded_fins
from .pieces import far_limit, pull_in
from .slabs import thickened
from .support import support_limit, weighed_fit
from .surface_triangles import edge_log_prob
from .thin import THIN_REACH, facing_away, lost_samples, thin_picks
from .uncapped import uncapped
from .winding import cell_winding

# The winding number reads 1 inside a closed input and 0 outside: a cell is inside where its number exceeds this.
CLOSED_THRESHOLD = 0.5
# Cutting through a triangle costs its area times (SMOOTH_FLOOR + 1 - p), p the face network's probability of its
# three edges (their geometric mean): where the network is sure the cut is nearly free, never quite.
SMOOTH_FLOOR = 0.05
# The face network's probability of a triangle with an added vertex (``solid_surface``'s ``extra``): neither way.
ADDED_P = 0.5
# The data term's weight against the smoothness term: labelling a cell against a winding number 0.5 from the
# threshold costs this times the area of its four triangles.
DATA_WEIGHT = 1.0
# A part of the input farther than this many support limits (``support.support_limit``) from the solid is lost.
LOST_LIMITS = 2.0
# An interface whose area is at most this share of the input's longest side squared encloses nothing.
FLAT_AREA = 1e-12
# The cells reach beyond the vertices' hull to their box grown by this share of its longest side.
BOX_MARGIN = 0.25


def face_costs(vertices: np.ndarray, tri: np.ndarray, edges: np.ndarray | None, logits: np.ndarray | None
               ) -> np.ndarray:
    """(T,) the cost of the surface passing through each triangle ``tri`` (T, 3): its area times
    ``SMOOTH_FLOOR + 1 - p``, p the geometric mean of its edges' probabilities under the face network
    (``surface_triangles.edge_log_prob``: the predicted ``edges`` (E, 2) at least 0.5; 0.5 without ``logits``)."""
    p = np.zeros(len(tri))
    # The network knows its own vertices only: a triangle on a corner of the box (``_box_corners``) gets p = 0.
    known = (tri < (len(vertices) if logits is None else len(logits))).all(1)
    t = tri[known]
    e = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [0, 2]]])
    p[known] = np.exp(edge_log_prob(e, logits, edges).reshape(3, -1).mean(0))
    return triangle_areas(vertices, tri) * (SMOOTH_FLOOR + 1.0 - p)


def solid_surface(vertices: np.ndarray, points: np.ndarray, normals: np.ndarray, edges: np.ndarray | None = None,
                  logits: np.ndarray | None = None, data_weight: float = DATA_WEIGHT,
                  seed: int = 0, extra: tuple[np.ndarray, np.ndarray] | None = None, known: dict | None = None,
                  thin_reach: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The boundary of the solid the input encloses among ``vertices``' Delaunay cells, wound outward.

    Parameters
    ----------
    vertices : (N, 3) float, at least 4 not on one plane
    points, normals : (P, 3) float, the input's oriented samples in the frame of ``vertices`` (normals outward)
    edges : (E, 2) int, optional, the face network's predicted edges
    logits : (N, N) float, optional, its edge logits
    data_weight : float
        The data term's weight against the smoothness term (``DATA_WEIGHT``).
    seed : int, of the samples the winding numbers sum over
    extra : (points (X, 3), normals (X, 3)) float, optional, more vertices: input samples on a thin part
        (``fastmesh.faces.thin``).  The face network never saw them: cutting through their triangles costs as
        through one it is unsure of (``ADDED_P``); a cell between them that their normals all face away from is
        inside (``thin.facing_away``, its edges at most ``thin_reach`` long)
    known : dict, optional, the cells' winding numbers read by an earlier cut of the same input
        (``winding.cell_winding``), filled with this one's
    thin_reach : float, see ``extra``

    Returns
    -------
    vertices : (M, 3) float64, those of ``vertices`` the surface uses
    faces : (F, 3) int64, every edge in two faces, wound alike; empty where no cell is inside
    """
    pts = np.asarray(points, dtype=np.float64)
    extra_points, extra_normals = (np.zeros((0, 3)), np.zeros((0, 3))) if extra is None else extra
    v, n = _cell_vertices(vertices, pts, extra_points)
    tets, nb = tetrahedralise(v)
    tri, a, b = cell_faces(tets, nb)
    # An input wound inside-out (an artist's mesh often is, in parts) reads -1 inside.
    w = np.abs(cell_winding(v, tets, points, normals, seed, known))
    if len(extra_points):
        w = np.where(facing_away(v, tets, n, extra_normals, thin_reach), np.maximum(w, CLOSED_THRESHOLD + 0.5), w)
    inside_cost, outside_cost = _label_costs(v, tets, w, CLOSED_THRESHOLD, data_weight)
    cost = _cut_costs(v, tri, edges, logits, n, len(extra_points))
    inside = min_cut(len(tets), inside_cost, outside_cost, a, b, cost)
    inside = made_manifold(tets, nb, tri, a, b, inside, inside_cost, outside_cost, len(v))
    f = interface(tri, a, b, inside)
    # Cells of a flat input are flat: an interface of no area encloses nothing (and cannot be weighed).
    if len(f) and triangle_areas(v, f).sum() <= FLAT_AREA * float(np.ptp(pts, axis=0).max()) ** 2:
        f = f[:0]
    v, f, _ = remove_unreferenced(v, f)
    return v, f


def _cell_vertices(vertices: np.ndarray, points: np.ndarray, extra: np.ndarray) -> tuple[np.ndarray, int]:
    """The corners of the cells: ``vertices`` (N, 3) pulled in to the input's samples ``points`` (P, 3), then the
    ``extra`` ones (X, 3), then the 8 corners of the box (:func:`_box_corners`); and N, where the extra ones start.

    A vertex farther than ``pieces.FAR_CELLS`` cells from the input moves onto it first, as the pipeline moves its
    result's (``pieces.pull_in``): moved after the cut, it would fold the solid."""
    v = pull_in(np.asarray(vertices, dtype=np.float64).reshape(-1, 3), points, far_limit(points))[0]
    return np.concatenate([v, extra, _box_corners(np.concatenate([v, points]))]), len(v)


def _label_costs(vertices: np.ndarray, tets: np.ndarray, winding: np.ndarray, threshold: float, data_weight: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(K,) each, what labelling each cell ``tets`` (K, 4) inside and outside costs, from its ``winding`` number
    (K,) against ``threshold``: nothing on the side the number reads, else up to the cell's boundary area times
    ``data_weight``.

    A cell the input is sure of keeps its label whatever its neighbours (however thin), an unsure one follows
    them."""
    size = cell_boundary_areas(vertices, tets) * data_weight
    # Near a sample the sum overshoots; the label reads only the side.
    w = np.clip(winding, threshold - 0.5, threshold + 0.5)
    w = 2.0 * (w - threshold)
    return size * np.maximum(-w, 0), size * np.maximum(w, 0)


def _cut_costs(vertices: np.ndarray, tri: np.ndarray, edges: np.ndarray | None, logits: np.ndarray | None,
               first: int, n_extra: int) -> np.ndarray:
    """(T,) what cutting through each triangle ``tri`` (T, 3) costs (:func:`face_costs`); one with an added vertex
    (``vertices[first:first + n_extra]``) and no corner of the box, which the face network never saw, costs as one
    it is unsure of (``ADDED_P``)."""
    cost = face_costs(vertices, tri, edges, logits)
    added = (tri >= first).any(1) & (tri < first + n_extra).all(1)
    cost[added] = triangle_areas(vertices, tri[added]) * (SMOOTH_FLOOR + 1.0 - ADDED_P)
    return cost


def with_thin_parts(vertices: np.ndarray, points: np.ndarray, normals: np.ndarray, edges: np.ndarray | None,
                    logits: np.ndarray | None, seed: int, thin: bool
                    ) -> tuple[np.ndarray, np.ndarray, int]:
    """:func:`solid_surface`, and with ``thin`` where it loses input samples, cut again with them among the
    vertices (``thin.thin_picks``), kept where fewer are lost; and how many added vertices the surface uses.
    The second cut reads again only the winding numbers of the cells the added vertices changed."""
    known: dict = {}
    v, f = solid_surface(vertices, points, normals, edges, logits, seed=seed, known=known)
    if not thin:
        return v, f, 0
    pts, nrm = np.asarray(points, dtype=np.float64), np.asarray(normals, dtype=np.float64)
    limit = support_limit(pts, 0.0)
    lost = lost_samples(pts, v, f, LOST_LIMITS * limit)
    pick, spacing = thin_picks(pts, nrm, lost, limit, len(vertices))
    if pick is None:
        return v, f, 0
    extra = pts[pick]
    tv, tf = solid_surface(vertices, pts, nrm, edges, logits, seed=seed, extra=(extra, nrm[pick]),
                           known=known, thin_reach=THIN_REACH * spacing)
    # Kept where it loses fewer samples and lies no farther from them (a cell it filled past the part would).
    if not len(tf) or lost_samples(pts, tv, tf, LOST_LIMITS * limit).sum() >= lost.sum() or (
            len(f) and weighed_fit(tv, tf, pts, seed) > weighed_fit(v, f, pts, seed)):
        return v, f, 0
    used = int((cKDTree(extra).query(tv)[0] == 0).sum())
    return tv, tf, used


def _not_crossing(vertices: np.ndarray, solid: np.ndarray, extra: np.ndarray) -> np.ndarray:
    """The ``extra`` faces (G, 3) that cross no face of ``solid`` (F, 3) or of ``extra`` sharing no vertex with it
    (``crossings.crossing_faces``): a part taken from the rival stops where it would pass through."""
    from .crossings import crossing_faces

    f = np.concatenate([solid, extra])
    mine = np.r_[np.zeros(len(solid), dtype=bool), np.ones(len(extra), dtype=bool)]
    return extra[~crossing_faces(vertices, f, among=mine)[len(solid):]]


def _box_corners(points: np.ndarray) -> np.ndarray:
    """(8, 3) the corners of the points' (P, 3) box grown by ``BOX_MARGIN`` of its longest side each way: with them
    the cells cover the input beyond its vertices' hull, and a sheet on that hull has cells behind it."""
    lo, hi = points.min(0), points.max(0)
    pad = BOX_MARGIN * max(float(np.max(hi - lo)), 1e-300)
    lo, hi = lo - pad, hi + pad
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])


def is_closed_surface(faces: np.ndarray) -> bool:
    """Every edge of ``faces`` (F, 3) in exactly two faces."""
    return bool(len(faces)) and bool((edge_face_counts(faces) == 2).all())


def solid_mesh(vertices: np.ndarray, points: np.ndarray, normals: np.ndarray, edges: np.ndarray | None,
               logits: np.ndarray | None, rival: tuple[np.ndarray, np.ndarray], reference: np.ndarray,
               margin: float, flat_tol: float | None = None, seed: int = 0, patch: bool = True, thin: bool = True,
               open_: bool = False) -> tuple[np.ndarray, np.ndarray, dict]:
    """The face stage's solid: :func:`solid_surface`, its flat vertices removed, weighed against ``rival`` (the
    surface selection's mesh on the same vertices).

    Where the decoder's vertices cannot enclose a part of the input (a wing or a boom one vertex thick), the cut
    loses it and lies farther from the input: the rival comes back where the solid's ``support.weighed_fit`` is over
    ``margin`` times the rival's, and the report says which came back.

    Parameters
    ----------
    vertices : (N, 3) float
    points, normals : (P, 3) float, the input's oriented samples (the winding numbers)
    edges : (E, 2) int or None; logits : (N, N) float or None, the face network's
    rival : (vertices (M, 3), faces (F, 3)), the surface selection's mesh
    reference : (R, 3) float, samples of the input both are weighed against
    margin : float
    flat_tol : float or None, as ``TriangleConfig.flat_tol`` (relative to the vertices' longest side)
    seed : int
    patch : bool
        Where the solid alone lies over ``margin`` times the rival's fit, the rival's faces that carry a part of
        the input the cut lost are added to it, as pieces of their own (:func:`lost_parts`; ``patched_faces``
        counts them), and that is weighed instead: where a piece stands for a thin solid part (the input on both
        its sides), it is made a thin closed part united with the solid (``slabs`` counts them); the other pieces
        stay sheets, and the result is no longer closed there.
    thin : bool
        Where the cut loses parts of the input, it is cut again with the input's samples there among the vertices
        (``fastmesh.faces.thin``; ``thin_vertices`` counts those the surface uses), kept where it loses fewer.
    open_ : bool
        The input is open: the solid that comes back loses its faces across the input's openings
        (``uncapped.uncapped``; ``uncapped_faces`` counts them), once weighed and patched as a closed one.

    Returns
    -------
    vertices, faces : the mesh that came back
    report : dict, ``fits`` {"solid", "surface"} (None where the cut left nothing inside), ``patched_faces``,
        ``slabs``, ``thin_vertices``, ``uncapped_faces`` and ``faces_from``
    """
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    f, added = np.zeros((0, 3), dtype=np.int64), 0
    if _spans_space(v):
        v, f, added = with_thin_parts(v, points, normals, edges, logits, seed, thin)
    if len(f) and flat_tol is not None:
        v, f = _without_flat(v, f, flat_tol)
    counts = {"patched_faces": 0, "slabs": 0, "thin_vertices": added, "uncapped_faces": 0}
    # The rival's fit, read once: the solid as cut and the solid patched are both weighed against it.
    theirs = round(weighed_fit(*rival, reference, seed), 6) if len(rival[1]) else float("inf")
    out = _weighed(v, f, rival, theirs, reference, margin, seed, counts)
    # The solid as the cut made it, closed, where it fits; else with the parts it lost from the rival.
    if out[2]["faces_from"] != "solid" and patch and len(f) and len(rival[1]):
        v, f, patched = _patched(v, f, rival, np.asarray(reference, dtype=np.float64), points, normals)
        out = _weighed(v, f, rival, theirs, reference, margin, seed, {**counts, **patched})
    # Closed while it is weighed and patched (the thin parts are united with a closed solid), then opened.
    if open_ and out[2]["faces_from"] == "solid":
        v, f, out[2]["uncapped_faces"] = uncapped(*out[:2], points, normals, seed)
        out = v, f, out[2]
    return out


def _spans_space(vertices: np.ndarray) -> bool:
    """At least 4 of the ``vertices`` (N, 3) and not all on one plane: they have Delaunay cells to label."""
    v = vertices
    return len(v) >= 4 and np.linalg.matrix_rank(v[1:] - v[0], tol=1e-9 * float(np.ptp(v, axis=0).max())) == 3


def _without_flat(vertices: np.ndarray, faces: np.ndarray, flat_tol: float) -> tuple[np.ndarray, np.ndarray]:
    """The surface with its flat vertices collapsed (``simplify.collapse_flat``, ``flat_tol`` relative to the
    vertices' longest side), or as it is where that would make it cross itself.

    Collapses see no faces but a vertex's own: where one folds the surface through another part, the cut's faces
    stay as they are."""
    from .defects import self_intersections
    from .simplify import collapse_flat

    flat = collapse_flat(vertices, faces, flat_tol * float(np.ptp(vertices, axis=0).max()), 1e-10)
    if self_intersections(vertices, flat) == 0:
        vertices, faces, _ = remove_unreferenced(vertices, flat)
    return vertices, faces


def _patched(vertices: np.ndarray, faces: np.ndarray, rival: tuple[np.ndarray, np.ndarray], reference: np.ndarray,
             points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict]:
    """The solid with the ``rival``'s faces that carry a part of the input (``reference`` (R, 3)) it lost
    (:func:`lost_parts`): each piece of them that stands for a thin solid part (the input's samples, ``points`` and
    ``normals`` (P, 3), on both its sides) made a thin closed part and united with the solid (``slabs.thickened``),
    the others kept as sheets where they cross none of its faces (:func:`_not_crossing`) and put no third face on
    its sides once welded (``meshops.welded_fins``); and the counts ``patched_faces`` (faces taken) and ``slabs``."""
    take = lost_parts(vertices, faces, *rival, reference)
    if not take.any():
        return vertices, faces, {"patched_faces": 0, "slabs": 0}
    both = np.concatenate([vertices, rival[0]])
    pts = np.asarray(points, dtype=np.float64)
    both, faces, rest, slabs = thickened(both, faces, rival[1][take] + len(vertices), pts, normals,
                                         LOST_LIMITS * support_limit(pts, 0.0))
    extra = _not_crossing(both, faces, rest)
    # A face along the solid's side, its corners the solid's own but not shared, is a fin once welded.
    extra = extra[~welded_fins(both, np.concatenate([faces, extra]))[len(faces):]]
    v, f, _ = remove_unreferenced(both, np.concatenate([faces, extra]))
    return v, f, {"patched_faces": int(take.sum()) - len(rest) + len(extra), "slabs": slabs}


def _weighed(vertices: np.ndarray, faces: np.ndarray, rival: tuple[np.ndarray, np.ndarray], theirs: float,
             reference: np.ndarray, margin: float, seed: int, counts: dict) -> tuple[np.ndarray, np.ndarray, dict]:
    """The solid, or the ``rival`` where the solid is empty or its ``support.weighed_fit`` to ``reference`` is over
    ``margin`` times ``theirs`` (the rival's); with :func:`solid_mesh`'s report (``counts``: ``patched_faces``,
    ``slabs``, ``thin_vertices``)."""
    ours = round(weighed_fit(vertices, faces, reference, seed), 6) if len(faces) else None
    report = {"fits": {"solid": ours, "surface": theirs}, **counts}
    if ours is None or ours > margin * theirs:
        return rival[0], rival[1], {**report, "faces_from": "surface"}
    return vertices, faces, {**report, "faces_from": "solid"}


def lost_parts(vertices: np.ndarray, faces: np.ndarray, rival_vertices: np.ndarray, rival_faces: np.ndarray,
               points: np.ndarray) -> np.ndarray:
    """(G,) bool, the faces of the rival (``rival_vertices`` (M, 3), ``rival_faces`` (G, 3)) that carry a part of
    the input the solid (``vertices`` (N, 3), ``faces`` (F, 3)) lost: each lies within ``LOST_LIMITS`` support
    limits of an input sample (``points`` (P, 3)) that far from the solid, and that far from the solid itself."""
    tol = LOST_LIMITS * support_limit(points, 0.0)
    lost = points[lost_samples(points, vertices, faces, tol)]
    if not len(lost):
        return np.zeros(len(rival_faces), dtype=bool)
    centre = rival_vertices[rival_faces].mean(1)
    near = cKDTree(lost).query(centre, distance_upper_bound=tol)[0] < np.inf
    if near.any():
        near[near] = lost_samples(centre[near], vertices, faces, tol)
    return near
