"""Faces chosen among candidates that lie on the input surface, kept a surface.

Candidates are the triangles of the vertices' 3D Delaunay tetrahedralisation that lie on the
input surface (a surface-restricted Delaunay triangulation: Delaunay triangles never cross each
other) plus the triangles of the face model's predicted edges that pass the same support test
(:func:`fastmesh.faces.support.support_distance`).  :func:`select_faces` takes them best first while the
result stays a surface: every edge in at most two faces, and no face folded onto a face it
shares an edge with.  :func:`fastmesh.faces.holes.fill_holes` then closes boundary loops, each face
checked against the input surface, so a closed input gives a closed result.

:func:`restricted_delaunay_mesh` is the anchor without learning: restricted Delaunay
triangles, best-supported first, at most two per edge.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .closure import close_loops, orientable
from .holes import fill_holes
from .orient import orient_faces, sides_asked
from .selection import Selection
from .support import support_distance, support_limit
from .triangles import TriangleConfig, drop_degenerate, limit_faces_per_edge

# Neighbourhoods whose least variance is under this share of the middle one count as flat.
_FLAT = 0.1
# Candidates whose normal is farther than acos(this) from the input surface's are dropped.
_MIN_FACING = 0.7
# Edge probability given to a pair the model scores lower (log-probabilities stay finite).
PROB_FLOOR = 1e-4


def delaunay_triangles(vertices: np.ndarray) -> np.ndarray:
    """(T, 3) int64 unique triangles (i < j < k) of the vertices' 3D Delaunay tetrahedralisation.

    Vertices all on one plane (or only three) have no tetrahedra: their 2D Delaunay
    triangulation in that plane is returned instead.
    """
    from scipy.spatial import Delaunay, QhullError

    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    if len(v) < 3:
        return np.zeros((0, 3), dtype=np.int64)
    centred = v - v.mean(0)
    _, s, vt = np.linalg.svd(centred, full_matrices=False)
    flat = len(v) < 4 or s[2] <= 1e-9 * max(s[0], 1e-300)
    try:
        if flat:
            tri = Delaunay(centred @ vt[:2].T).simplices
            return np.unique(np.sort(tri, axis=1), axis=0).astype(np.int64)
        tets = Delaunay(v).simplices  # (K, 4)
    except QhullError:  # collinear or otherwise degenerate input: no triangles
        return np.zeros((0, 3), dtype=np.int64)
    t = tets[:, [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]]].reshape(-1, 3)
    return np.unique(np.sort(t, axis=1), axis=0).astype(np.int64)


def on_surface(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, tol: float = 0.0,
               tree: cKDTree | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """The faces whose inner points lie on the input surface.

    Parameters
    ----------
    vertices : (N, 3) float
    faces : (F, 3) int
    points : (P, 3) float, samples of the input surface (at least two)
    tol : float
        Relative to the points' longest side; the limit is at least ``SPACING_FACTOR`` point spacings
        (:func:`fastmesh.faces.support.support_limit`).
    tree : cKDTree of ``points``, optional

    Returns
    -------
    faces : (F', 3) int64, the supported ones, non-degenerate
    distance : (F',) float64, their support distance
    limit : float
    """
    v = np.asarray(vertices, dtype=np.float64)
    tree = tree if tree is not None else cKDTree(np.asarray(points, dtype=np.float64))
    limit = support_limit(points, tol, tree)
    f = drop_degenerate(v, faces)
    d = support_distance(v, f, points, tree)
    keep = d <= limit
    return f[keep], d[keep], limit


def restricted_delaunay_mesh(vertices: np.ndarray, points: np.ndarray, tol: float = 0.0) -> np.ndarray:
    """The no-learning anchor: restricted Delaunay triangles, best-supported first while each edge has
    fewer than two faces, oriented.

    Returns
    -------
    (F, 3) int64 faces into ``vertices``.
    """
    f, d, _ = on_surface(vertices, delaunay_triangles(vertices), points, tol)
    return orient_faces(vertices, limit_faces_per_edge(f, d, 2))


def edge_log_prob(edges: np.ndarray, logits: np.ndarray | None, predicted: np.ndarray | None = None) -> np.ndarray:
    """(E,) log-probability of each edge under the face model.

    Parameters
    ----------
    edges : (E, 2) int
    logits : (N, N) float edge logits (symmetrised here), or None (every edge gets probability 0.5)
    predicted : (K, 2) int, optional
        The edges the model finally predicted (after filtering): they get at least probability 0.5.
    """
    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    if logits is None:
        p = np.full(len(e), 0.5)
    else:
        lg = (logits[e[:, 0], e[:, 1]].astype(np.float64) + logits[e[:, 1], e[:, 0]]) / 2
        p = 1 / (1 + np.exp(-lg))
    if predicted is not None and len(predicted) and len(e):
        n = int(max(e.max(), np.max(predicted))) + 1
        pk = np.sort(np.asarray(predicted, dtype=np.int64), axis=1)
        hit = np.isin(np.sort(e, axis=1) @ np.array([n, 1]), pk @ np.array([n, 1]))
        p = np.where(hit, np.maximum(p, 0.5), p)
    return np.log(np.maximum(p, PROB_FLOOR))


def _plane_fit(at: np.ndarray, points: np.ndarray, tree: cKDTree, k: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Normal (M, 3) of the ``k`` input points nearest each of ``at`` (M, 3), and whether they are flat
    (M,) bool: their least variance under ``_FLAT`` times the middle one."""
    _, idx = tree.query(at, k=min(k, len(points)))
    nb = points[idx.reshape(len(at), -1)]  # (M, k, 3)
    d = nb - nb.mean(1)[:, None]
    w, vec = np.linalg.eigh(np.einsum("nki,nkj->nij", d, d))
    return vec[:, :, 0], w[:, 0] <= _FLAT * w[:, 1]


def facing(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, tree: cKDTree | None = None) -> np.ndarray:
    """(F,) |cosine| between each face's normal and the input surface's normal at its centroid (1 where
    the surface there is not flat).  A sliver along a curved surface (three vertices of one ring of a
    cylinder) lies close to the surface but across it: its cosine is near 0."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(f) == 0:
        return np.zeros(0)
    pts = np.asarray(points, dtype=np.float64)
    tree = tree if tree is not None else cKDTree(pts)
    t = v[f]
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    normal, flat = _plane_fit(t.mean(1), pts, tree)
    return np.where(flat, np.abs((n * normal).sum(1)), 1.0)


def vertex_frames(vertices: np.ndarray, points: np.ndarray, tree: cKDTree | None = None,
                  k: int = 16) -> np.ndarray:
    """(N, 2, 3) two orthonormal tangent directions of the input surface at each vertex; NaN where the
    ``k`` nearest input points do not lie near one plane (no tangent plane to compare faces in).
    """
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    pts = np.asarray(points, dtype=np.float64)
    normal, flat = _plane_fit(v, pts, tree if tree is not None else cKDTree(pts), k)
    helper = np.where(np.abs(normal[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    t1 = np.cross(normal, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    frames = np.stack([t1, np.cross(normal, t1)], axis=1)
    frames[~flat] = np.nan
    return frames


def select_faces(vertices: np.ndarray, faces: np.ndarray, score: np.ndarray, frames: np.ndarray,
                 fold_angle: float = 30.0, side: np.ndarray | None = None) -> tuple[np.ndarray, Selection]:
    """Faces best first (highest ``score``) while the result stays a surface.

    A face is taken when none of its edges already has two faces and it folds onto no selected face
    it shares an edge with (angle between the two around the edge under ``fold_angle`` degrees: the
    two would overlap, as both diagonal splits of a quad do), nor overlaps a selected face around a
    shared corner in the tangent plane there (``frames``: (N, 2, 3) from :func:`vertex_frames`), and every
    piece stays one that can be wound one way facing the input (``side`` (F,): :func:`orient.sides_asked` of
    ``faces``; ``selection.Windings``).

    Returns
    -------
    faces : (F', 3) int64, selection order
    edges : the per-edge bookkeeping, for :func:`fill_holes`
    """
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    book = Selection(vertices, frames, fold_angle)
    order = np.argsort(-np.asarray(score), kind="stable")
    asked = np.full(len(f), -1) if side is None else np.asarray(side)
    out = []
    for (a, b, c), s in zip(f[order].tolist(), asked[order].tolist(), strict=True):
        prefer = None if s < 0 else s
        if book.fits(a, b, c, prefer):
            book.add(a, b, c, prefer)
            out.append((a, b, c))
    return np.asarray(out, dtype=np.int64).reshape(-1, 3), book


def surface_mesh(vertices: np.ndarray, edges: np.ndarray, points: np.ndarray, config: TriangleConfig | None = None,
                 logits: np.ndarray | None = None, oriented: tuple[np.ndarray, np.ndarray] | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Faces among the surface candidates, chosen by the model, kept a surface, holes closed.

    Parameters
    ----------
    vertices : (N, 3) float
    edges : (E, 2) int, the model's predicted edges
    points : (P, 3) float, samples of the input surface in the frame of ``vertices``
    config : TriangleConfig
        ``surface_tol``, ``fold_angle``, ``fill_max_loop``, ``model_weight``, ``close``, ``close_everywhere``.
    logits : (N, N) float, optional
        The model's edge logits: a triangle scores ``model_weight`` times the mean log-probability of
        its edges minus its support distance in units of the limit.  Without them the
        best-supported triangles come first.
    oriented : (points (Q, 3), normals (Q, 3)), optional
        The input's samples with their normals: no piece joins faces they ask to face opposite ways
        (:func:`select_faces`).

    Returns
    -------
    vertices : (N + k, 3) float64, ``vertices`` and the k vertices the closure added (``config.close``)
    faces : (F, 3) int64, oriented
    """
    cfg = config or TriangleConfig()
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    pts = np.asarray(points, dtype=np.float64)
    cand = delaunay_triangles(v)
    cand = np.unique(np.sort(cand, axis=1), axis=0) if len(cand) else cand.reshape(0, 3)
    tree = cKDTree(pts)
    f, d, limit = on_surface(v, cand, pts, cfg.surface_tol or 0.0, tree)
    keep = facing(v, f, pts, tree) >= _MIN_FACING
    f, d = f[keep], d[keep]
    score = -d / limit
    if logits is not None and len(f):
        lp = edge_log_prob(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [0, 2]]]), logits, edges)
        score = score + cfg.model_weight * lp.reshape(3, -1).mean(0)
    side = None if oriented is None else sides_asked(v, f, *oriented)
    return _kept_surface(v, f, score, pts, tree, limit, cfg, side=side)


def surface_from_faces(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray,
                       config: TriangleConfig | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Given faces made a surface by the rules the face stage applies to its own, and their holes closed as it
    closes its own: a mesh that is not an asset (an edge in three faces, windings that disagree, open where the
    input is closed; a quadric decimation can be all of these) made one.

    Parameters
    ----------
    vertices : (N, 3) float
    faces : (F, 3) int
    points : (P, 3) float, samples of the input surface in the frame of ``vertices``
    config : TriangleConfig
        ``surface_tol``, ``fold_angle``, ``fill_max_loop``, ``close``, ``close_everywhere``.

    Returns
    -------
    vertices : (N + k, 3) float64, ``vertices`` and the k vertices the closure added (``config.close``)
    faces : (F', 3) int64, oriented, each edge in at most two faces: of ``faces``, those on the input surface,
        the nearest first where some break the rules together; then the faces that fill and close holes
    """
    cfg = config or TriangleConfig()
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    pts = np.asarray(points, dtype=np.float64)
    tree = cKDTree(pts)
    f, d, limit = on_surface(v, np.asarray(faces, dtype=np.int64).reshape(-1, 3), pts, cfg.surface_tol or 0.0, tree)
    # Not the face stage's own triangles: a decimation's may twist (a thin part's two sides joined), so the faces
    # that keep the windings from agreeing go before the holes are filled, closed or not.
    return _kept_surface(v, f, -d / limit, pts, tree, limit, cfg, twisted=True)


def _kept_surface(v: np.ndarray, f: np.ndarray, score: np.ndarray, pts: np.ndarray, tree: cKDTree, limit: float,
                  cfg: TriangleConfig, twisted: bool = False, side: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Faces ``f`` best ``score`` first while they stay a surface (:func:`select_faces`, with the ``side`` the
    input asks of each), oriented (``twisted``: less the faces that keep them from it, ``closure.orientable``),
    holes filled and (``cfg.close``) closed within the support ``limit``: (vertices, faces)."""
    f, book = select_faces(v, f, score, vertex_frames(v, pts, tree), cfg.fold_angle, side)
    f = orientable(v, f, book) if twisted else orient_faces(v, f)  # boundary loops follow the windings
    if cfg.fill_max_loop:
        f = orient_faces(v, fill_holes(v, f, book, pts, limit, tree, cfg.fill_max_loop))
    if cfg.close:
        v, f = close_loops(v, f, book, pts, limit, tree, bounded=not cfg.close_everywhere)
        f = orient_faces(v, f)
    return v, orientable(v, f, book) if twisted else f
