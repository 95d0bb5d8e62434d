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

import math

import numpy as np
from scipy.spatial import cKDTree

from .closure import close_loops
from .holes import fill_holes
from .support import support_distance, support_limit
from .triangles import TriangleConfig, drop_degenerate, limit_faces_per_edge, orient_faces, triangles_from_adjacency

# Share of the narrower corner two faces around a vertex may overlap in the tangent plane there
# (projection onto an estimated plane is inexact on curved and sharp parts).
_SECTOR_SLACK = 0.25
# Neighbourhoods whose least variance is under this share of the middle one count as flat.
_FLAT = 0.1
# Candidates whose normal is farther than acos(this) from the input surface's are dropped.
_MIN_FACING = 0.7
# A face farther than acos(this) from a vertex's tangent plane is not compared in that plane.
_CREASE = 0.5
# Faces at a vertex without a usable tangent plane overlap only when closer than acos(this) in angle.
_PARALLEL = 0.9
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


def _folded(v: list, a: int, b: int, c: int, d: int, min_cos: float) -> bool:
    """Whether faces (a, b, c) and (a, b, d) fold onto each other across edge (a, b): the angle between
    them around the edge is below the one whose cosine is ``min_cos``."""
    ax, ay, az = v[a]
    ex, ey, ez = v[b][0] - ax, v[b][1] - ay, v[b][2] - az
    ee = ex * ex + ey * ey + ez * ez or 1e-300
    out = []
    for w in (c, d):
        px, py, pz = v[w][0] - ax, v[w][1] - ay, v[w][2] - az
        k = (px * ex + py * ey + pz * ez) / ee
        out.append((px - k * ex, py - k * ey, pz - k * ez))
    (ux, uy, uz), (wx, wy, wz) = out
    nu = math.sqrt(ux * ux + uy * uy + uz * uz) * math.sqrt(wx * wx + wy * wy + wz * wz)
    return nu == 0 or (ux * wx + uy * wy + uz * wz) / nu > min_cos


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


def _cross(a, b) -> list[float]:
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def _unit(a) -> list[float]:
    n = math.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2]) or 1e-300
    return [a[0] / n, a[1] / n, a[2] / n]


def _normal(v: list, a: int, b: int, c: int) -> list[float]:
    """Unit normal of triangle (a, b, c) of the vertex list ``v``."""
    return _unit(_cross([v[b][i] - v[a][i] for i in range(3)], [v[c][i] - v[a][i] for i in range(3)]))


def _arc(v: list, a: int, b: int, c: int, frame) -> tuple[float, float]:
    """(start, width) in radians of the corner at ``a`` of triangle (a, b, c), projected onto the plane
    of ``frame`` (two orthonormal directions)."""
    (ux, uy, uz), (wx, wy, wz) = frame
    ax, ay, az = v[a]
    ang = []
    for x in (b, c):
        px, py, pz = v[x][0] - ax, v[x][1] - ay, v[x][2] - az
        ang.append(math.atan2(px * wx + py * wy + pz * wz, px * ux + py * uy + pz * uz))
    lo, hi = min(ang), max(ang)
    return (lo, hi - lo) if hi - lo <= math.pi else (hi, 2 * math.pi - (hi - lo))


def _arcs_overlap(s0: float, w0: float, s1: float, w1: float) -> bool:
    """Whether arcs [s0, s0 + w0] and [s1, s1 + w1] of the circle share more than ``_SECTOR_SLACK`` of
    the narrower one."""
    d = (s1 - s0) % (2 * math.pi)
    inter = max(min(w0, d + w1) - d, 0.0) + max(min(w1, 2 * math.pi - d + w0) - (2 * math.pi - d), 0.0)
    return inter > _SECTOR_SLACK * min(w0, w1)


class _Selection:
    """The selected faces' bookkeeping: third vertices on each edge, and the angular sector each face
    covers around each of its corners in the tangent plane there (faces around a vertex must not
    overlap), and each face's normal.  A corner whose face lies farther than acos(``_CREASE``) from the
    vertex's tangent plane (across a crease or a corner the nearest points miss) has no sector there:
    see :meth:`_overlaps`.  ``open`` holds the boundary: each vertex's neighbours across an edge of
    one face, kept with ``third`` so that hole filling walks it without visiting every face at a vertex."""

    def __init__(self, vertices: np.ndarray, frames: np.ndarray, fold_angle: float):
        self.v = np.asarray(vertices, dtype=np.float64).tolist()
        fr = np.asarray(frames, dtype=np.float64)
        self.frames = fr.tolist()
        self.normals = np.cross(fr[:, 0], fr[:, 1]).tolist()
        self.min_cos = math.cos(math.radians(fold_angle))
        self.third: dict[tuple[int, int], list[int]] = {}
        self.sectors: dict[int, dict[tuple[int, int, int], tuple[float, float]]] = {}
        self.face_normals: dict[tuple[int, int, int], list[float]] = {}
        self.open: dict[int, set[int]] = {}

    def add_vertex(self, position: np.ndarray) -> None:
        """A vertex after the others (the closure's), with no tangent plane: its corners have no sector."""
        self.v.append([float(x) for x in position])
        self.frames.append([[math.nan] * 3, [math.nan] * 3])
        self.normals.append([math.nan] * 3)

    def _sector(self, a: int, b: int, c: int, f: list[float]) -> tuple[float, float]:
        """(start, width) in radians of the corner of face (a, b, c) (unit normal ``f``) at ``a``, seen in
        a's tangent plane; NaN where a has no tangent plane or the face lies across it."""
        n = self.normals[a]
        if not abs(f[0] * n[0] + f[1] * n[1] + f[2] * n[2]) >= _CREASE:  # also False with a NaN frame
            return (math.nan, math.nan)
        return _arc(self.v, a, b, c, self.frames[a])

    def _overlaps(self, a: int, b: int, c: int, n: list[float]) -> bool:
        """Whether the corner of face (a, b, c) (unit normal ``n``) at ``a`` overlaps a selected face's
        corner there.

        In a's tangent plane where both corners have a sector there; otherwise (a crease, a corner, a
        face across the plane) only a selected face nearly parallel to this one can overlap it, and the
        two are compared in this face's own plane.
        """
        s0, w0 = self._sector(a, b, c, n)
        own = None
        for key, (s1, w1) in self.sectors.get(a, {}).items():
            if not (math.isnan(s0) or math.isnan(s1)):
                if _arcs_overlap(s0, w0, s1, w1):
                    return True
                continue
            if own is None:
                e = [self.v[b][i] - self.v[a][i] for i in range(3)]
                k = sum(e[i] * n[i] for i in range(3))
                u = _unit([e[i] - k * n[i] for i in range(3)])
                frame = (u, _cross(n, u))
                own = (frame, _arc(self.v, a, b, c, frame))
            frame, (s2, w2) = own
            m = self.face_normals[key]
            if abs(n[0] * m[0] + n[1] * m[1] + n[2] * m[2]) < _PARALLEL:
                continue
            y, z = (x for x in key if x != a)
            if _arcs_overlap(s2, w2, *_arc(self.v, a, y, z, frame)):
                return True
        return False

    def fits(self, a: int, b: int, c: int) -> bool:
        """Face (a, b, c) keeps every edge in at most two faces, folds onto no neighbour across an
        edge, and overlaps no selected face around any of its corners."""
        for x, y, z in ((a, b, c), (b, c, a), (a, c, b)):
            others = self.third.get((x, y) if x < y else (y, x), ())
            if len(others) >= 2 or any(_folded(self.v, x, y, o, z, self.min_cos) for o in others):
                return False
        n = _normal(self.v, a, b, c)  # the same for every corner: they turn the same way
        return not any(self._overlaps(x, y, z, n) for x, y, z in ((a, b, c), (b, c, a), (c, a, b)))

    def _edge_count_changed(self, x: int, y: int, n: int) -> None:
        """Edge (x, y) is now in ``n`` faces: on the boundary exactly when n is 1."""
        if n == 1:
            self.open.setdefault(x, set()).add(y)
            self.open.setdefault(y, set()).add(x)
        else:
            self.open.get(x, set()).discard(y)
            self.open.get(y, set()).discard(x)

    def add(self, a: int, b: int, c: int) -> None:
        for x, y, z in ((a, b, c), (b, c, a), (a, c, b)):
            others = self.third.setdefault((x, y) if x < y else (y, x), [])
            others.append(z)
            self._edge_count_changed(x, y, len(others))
        key = tuple(sorted((a, b, c)))  # any winding of the face names it
        n = self.face_normals[key] = _normal(self.v, a, b, c)
        for x, y, z in ((a, b, c), (b, c, a), (c, a, b)):
            self.sectors.setdefault(x, {})[key] = self._sector(x, y, z, n)

    def remove(self, a: int, b: int, c: int) -> None:
        for x, y, z in ((a, b, c), (b, c, a), (a, c, b)):
            others = self.third[(x, y) if x < y else (y, x)]
            others.remove(z)
            self._edge_count_changed(x, y, len(others))
        key = tuple(sorted((a, b, c)))
        del self.face_normals[key]
        for x in (a, b, c):
            del self.sectors[x][key]


def select_faces(vertices: np.ndarray, faces: np.ndarray, score: np.ndarray, frames: np.ndarray,
                 fold_angle: float = 30.0) -> tuple[np.ndarray, _Selection]:
    """Faces best first (highest ``score``) while the result stays a surface.

    A face is taken when none of its edges already has two faces and it folds onto no selected face
    it shares an edge with (angle between the two around the edge under ``fold_angle`` degrees: the
    two would overlap, as both diagonal splits of a quad do), nor overlaps a selected face around a
    shared corner in the tangent plane there (``frames``: (N, 2, 3) from :func:`vertex_frames`).

    Returns
    -------
    faces : (F', 3) int64, selection order
    edges : the per-edge bookkeeping, for :func:`fill_holes`
    """
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    book = _Selection(vertices, frames, fold_angle)
    out = []
    for a, b, c in f[np.argsort(-np.asarray(score), kind="stable")].tolist():
        if book.fits(a, b, c):
            book.add(a, b, c)
            out.append((a, b, c))
    return np.asarray(out, dtype=np.int64).reshape(-1, 3), book


def surface_mesh(vertices: np.ndarray, edges: np.ndarray, points: np.ndarray, config: TriangleConfig | None = None,
                 logits: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Faces among the surface candidates, chosen by the model, kept a surface, holes closed.

    Parameters
    ----------
    vertices : (N, 3) float
    edges : (E, 2) int, the model's predicted edges
    points : (P, 3) float, samples of the input surface in the frame of ``vertices``
    config : TriangleConfig
        ``surface_tol``, ``fold_angle``, ``fill_max_loop``,
        ``support_weight``, ``model_weight``, ``model_triangles``, ``close``.
    logits : (N, N) float, optional
        The model's edge logits: a triangle scores ``model_weight`` times the mean log-probability of
        its edges minus ``support_weight`` times its support distance in units of the limit.  Without them the
        best-supported triangles come first.

    Returns
    -------
    vertices : (N + k, 3) float64, ``vertices`` and the k vertices the closure added (``config.close``)
    faces : (F, 3) int64, oriented
    """
    cfg = config or TriangleConfig()
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    pts = np.asarray(points, dtype=np.float64)
    cand = delaunay_triangles(v)
    if cfg.model_triangles:
        cand = np.concatenate([cand, triangles_from_adjacency(edges, len(v))])
    cand = np.unique(np.sort(cand, axis=1), axis=0) if len(cand) else cand.reshape(0, 3)
    tree = cKDTree(pts)
    f, d, limit = on_surface(v, cand, pts, cfg.surface_tol or 0.0, tree)
    keep = facing(v, f, pts, tree) >= _MIN_FACING
    f, d = f[keep], d[keep]
    score = -cfg.support_weight * d / limit
    if logits is not None and len(f):
        lp = edge_log_prob(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [0, 2]]]), logits, edges)
        score = score + cfg.model_weight * lp.reshape(3, -1).mean(0)
    f, book = select_faces(v, f, score, vertex_frames(v, pts, tree), cfg.fold_angle)
    f = orient_faces(v, f)  # boundary loops follow the windings
    if cfg.fill_max_loop:
        f = orient_faces(v, fill_holes(v, f, book, pts, limit, tree, cfg.fill_max_loop))
    if cfg.close:
        v, f = close_loops(v, f, book, pts, limit, tree)
        f = orient_faces(v, f)
    return v, f
