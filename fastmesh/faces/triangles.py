"""Faces from a predicted adjacency: triangles of mutually connected vertex triplets, then clean-up.

The face stage predicts edges; faces are the 3-cycles of the edge graph.  Enumeration is
vectorised: vertices are ranked by degree, every edge points from lower to higher rank,
and a triangle is found once as a wedge ``x -> y -> z`` closed by the edge ``x -> z``
(with degree ranking each vertex has at most sqrt(2E) out-neighbours, so the wedges stay
few even for dense predictions).

Not every 3-cycle is a face (three faces around a valence-3 vertex close a 3-cycle over its
ring, a flat quad with both diagonals gives four triangles), so :func:`fastmesh.faces.mesh_from_adjacency`
optionally drops zero-area triangles and one diagonal of coplanar 4-cliques (the variant in
the authors' release), then orients the faces consistently and outward.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..tokenizer.grid import CELL
from .meshops import normalize_edges, triangle_areas

# Wedges expanded per vectorised chunk: bounds memory at ~100 MB for any adjacency.
_CHUNK = 2_000_000


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
    flat_tol : float or None
        Last, remove the vertices of flat regions, straight creases and straight open borders
        (:func:`fastmesh.faces.simplify.collapse_flat`): a kept vertex stays within ``flat_tol * L``
        of the faces it replaces (None: keep every vertex).  Default: half a 7-bit cell.  The pipeline
        turns it off for a face-count target (the count asked for).
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
    flat_tol: float | None = 0.5 * CELL

    def __post_init__(self):
        if self.selection not in ("cliques", "surface"):
            raise ValueError(f"selection must be 'cliques' or 'surface', got {self.selection!r}")


# --------------------------------------------------------------------------- graphs


def as_edges(adj, n_vertices: int | None = None) -> tuple[np.ndarray, int]:
    """Normalise an adjacency to ``(edges (E, 2) int64 with i < j, unique, sorted; N)``.

    Parameters
    ----------
    adj : (N, N) array (bool or numeric; non-zero = edge), scipy sparse matrix, or (E, 2) int edge list
        Directed entries are symmetrised (an edge in either direction counts); the diagonal
        is ignored.  A square (2, 2) array is read as a matrix.
    n_vertices : int, optional
        N for an edge list (default: largest index + 1).
    """
    import scipy.sparse as sp

    if sp.issparse(adj):
        coo = sp.coo_matrix(adj)
        nz = coo.data != 0
        e, n = np.stack([coo.row[nz], coo.col[nz]], axis=1), coo.shape[0]
    else:
        a = np.asarray(adj)
        if a.ndim == 2 and a.shape[0] == a.shape[1] and a.shape[0] > 0:
            e, n = np.argwhere(a != 0), a.shape[0]
        elif (a.ndim == 2 and a.shape[1] == 2) or a.size == 0:
            e = a.reshape(-1, 2).astype(np.int64)
            n = int(e.max()) + 1 if len(e) else 0
        else:
            raise ValueError(f"adjacency must be N x N or E x 2, got shape {a.shape}")
    n = int(n_vertices) if n_vertices is not None else n
    e = normalize_edges(e)
    if len(e) and (e.min() < 0 or e.max() >= n):
        raise ValueError("edge index out of range")
    return e, n


class _RankedGraph:
    """Edges oriented from lower to higher (degree, index) rank, as CSR in rank space."""

    def __init__(self, edges: np.ndarray, n: int):
        deg = np.bincount(edges.ravel(), minlength=n)
        self.order = np.lexsort((np.arange(n), deg))  # rank -> vertex
        rank = np.empty(n, dtype=np.int64)
        rank[self.order] = np.arange(n)
        r = np.sort(rank[edges], axis=1)
        r = r[np.lexsort((r[:, 1], r[:, 0]))]
        self.n = n
        self.tails, self.heads = r[:, 0], r[:, 1]
        self.indptr = np.concatenate([[0], np.cumsum(np.bincount(self.tails, minlength=n))])
        self.keys = self.tails * n + self.heads  # ascending

    def has_edge(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Vectorised membership of rank-space edges x -> y (x < y)."""
        k = x * self.n + y
        pos = np.minimum(np.searchsorted(self.keys, k), max(len(self.keys) - 1, 0))
        return self.keys[pos] == k if len(self.keys) else np.zeros(len(k), dtype=bool)

    def extend(self, rows: np.ndarray):
        """Yield chunks of ``rows`` (R, m) extended by every out-neighbour of their last column."""
        last = rows[:, -1]
        cnt = self.indptr[last + 1] - self.indptr[last]
        ends = np.cumsum(cnt)
        lo = 0
        while lo < len(rows):
            # rows [lo, hi) expand to at most _CHUNK wedges (at least one row per chunk)
            hi = max(lo + 1, int(np.searchsorted(ends, (ends[lo - 1] if lo else 0) + _CHUNK, side="right")))
            c = cnt[lo:hi]
            rep = np.repeat(np.arange(lo, hi), c)
            within = np.arange(len(rep)) - np.repeat(np.cumsum(c) - c, c)
            nxt = self.heads[self.indptr[last[rep]] + within]
            yield np.concatenate([rows[rep], nxt[:, None]], axis=1)
            lo = hi


def triangles_from_adjacency(adj, n_vertices: int | None = None) -> np.ndarray:
    """All 3-cycles of an adjacency.

    Returns
    -------
    (T, 3) int64 vertex triplets (i < j < k), rows sorted; unoriented.
    """
    edges, n = as_edges(adj, n_vertices)
    if len(edges) < 3:
        return np.zeros((0, 3), dtype=np.int64)
    g = _RankedGraph(edges, n)
    pairs = np.stack([g.tails, g.heads], axis=1)
    tri = [w[g.has_edge(w[:, 0], w[:, 2])] for w in g.extend(pairs)]
    tri = np.concatenate(tri) if tri else np.zeros((0, 3), dtype=np.int64)
    return _sorted_rows(g.order[tri])


def cliques4(adj, n_vertices: int | None = None) -> np.ndarray:
    """All 4-cliques: (K, 4) int64 sorted vertex quadruples."""
    edges, n = as_edges(adj, n_vertices)
    if len(edges) < 6:
        return np.zeros((0, 4), dtype=np.int64)
    g = _RankedGraph(edges, n)
    pairs = np.stack([g.tails, g.heads], axis=1)
    tri = np.concatenate([w[g.has_edge(w[:, 0], w[:, 2])] for w in g.extend(pairs)])
    quads = [w[g.has_edge(w[:, 0], w[:, 3]) & g.has_edge(w[:, 1], w[:, 3])] for w in g.extend(tri)] if len(tri) else []
    quads = np.concatenate(quads) if quads else np.zeros((0, 4), dtype=np.int64)
    return _sorted_rows(g.order[quads])


def _sorted_rows(a: np.ndarray) -> np.ndarray:
    a = np.sort(a, axis=1)
    return a[np.lexsort(a.T[::-1])] if len(a) else a.reshape(0, a.shape[1])


# --------------------------------------------------------------------------- clean-up


def _scale(vertices: np.ndarray) -> float:
    return float(np.ptp(vertices, axis=0).max()) if len(vertices) else 1.0


def drop_degenerate(vertices: np.ndarray, faces: np.ndarray, area_tol: float = 1e-10) -> np.ndarray:
    """Drop faces with a repeated index or an area at most ``area_tol * L**2``; then duplicates
    (the same vertex set, whatever the winding; the first one is kept)."""
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    ok = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
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
    p = v[quads]  # (K, 4, 3)
    # The four triangles of each clique, triangle t leaves out point t.
    omit = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])
    t = p[:, omit]  # (K, 4, 3, 3)
    cr = np.cross(t[:, :, 1] - t[:, :, 0], t[:, :, 2] - t[:, :, 0])  # (K, 4, 3)
    area2 = np.linalg.norm(cr, axis=2)
    big = area2.argmax(1)  # most stable plane: the largest triangle
    k = np.arange(len(quads))
    normal = cr[k, big] / np.maximum(area2[k, big, None], 1e-300)
    dist = np.abs(((p[k, big] - t[k, big, 0]) * normal).sum(1))
    flat = (dist <= coplanar_tol * _scale(v)) & (area2[k, big] > 0)
    # Pairings of the four points into two segments; the crossing pair is the quad's diagonals.
    pairings = np.array([[0, 1, 2, 3], [0, 2, 1, 3], [0, 3, 1, 2]])
    a, b, c, d = (p[:, pairings[:, i]] for i in range(4))  # (K, 3, 3) each

    def side(o, e, x):  # sign of x relative to the line o-e, within the plane
        return (np.cross(e - o, x - o) * normal[:, None]).sum(-1)

    cross = (side(a, b, c) * side(a, b, d) < 0) & (side(c, d, a) * side(c, d, b) < 0)  # (K, 3)
    convex = flat & (cross.sum(1) == 1) & ("convex" in cases)
    inner = flat & (cross.sum(1) == 0) & ("inner" in cases)
    drop_edges = np.zeros((0, 2), dtype=np.int64)
    if convex.any():
        kk = np.flatnonzero(convex)
        pi = cross[kk].argmax(1)
        pa, pb = quads[kk[:, None], pairings[pi][:, :2]], quads[kk[:, None], pairings[pi][:, 2:]]
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
        outer = np.sort(quads[kk[:, None], omit[big[kk]]], axis=1)
        fs = np.sort(f, axis=1)
        keep &= ~np.isin((fs[:, 0] * n + fs[:, 1]) * n + fs[:, 2], (outer[:, 0] * n + outer[:, 1]) * n + outer[:, 2])
    return f[keep]


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


def orient_faces(vertices: np.ndarray, faces: np.ndarray, outward: bool = True) -> np.ndarray:
    """Consistent winding across edges shared by exactly two faces, then each part outward.

    A breadth-first spanning forest of the face graph (one traversal from a virtual root
    linked to every part) fixes each face's flip relative to its part's root; the flips
    accumulate along the tree by pointer jumping (vectorised, O(F log depth)).  Edges with
    more than two faces do not constrain winding.  With ``outward``, a part whose signed
    volume about the vertex centroid is negative is flipped (exact for closed parts, a
    heuristic for open ones).

    Returns
    -------
    (F, 3) int64 faces, same order, some reversed.
    """
    import scipy.sparse as sp
    from scipy.sparse.csgraph import breadth_first_order, connected_components

    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3).copy()
    nf = len(f)
    if nf == 0:
        return f
    he = np.stack([f, np.roll(f, -1, axis=1)], axis=2).reshape(-1, 2)  # half-edges (3F, 2), face = index // 3
    key = np.sort(he, axis=1) @ np.array([len(vertices), 1])
    order = np.argsort(key, kind="stable")
    ks = key[order]
    start = np.flatnonzero(np.r_[True, ks[1:] != ks[:-1]])
    count = np.diff(np.r_[start, len(ks)])
    two = start[count == 2]
    h1, h2 = order[two], order[two + 1]
    fa, fb = h1 // 3, h2 // 3
    same_dir = he[h1, 0] == he[h2, 0]  # equal directions: one of the two must flip
    ok = fa != fb
    fa, fb, same_dir = fa[ok], fb[ok], same_dir[ok]
    g = sp.coo_matrix((np.ones(len(fa)), (fa, fb)), shape=(nf + 1, nf + 1)).tocsr()
    _, label = connected_components(g[:nf, :nf], directed=False)
    roots = np.unique(label, return_index=True)[1]
    g = g + sp.coo_matrix((np.ones(len(roots)), (np.full(len(roots), nf), roots)), shape=(nf + 1, nf + 1)).tocsr()
    _, pred = breadth_first_order(g, nf, directed=False, return_predecessors=True)
    pred = pred[:nf]
    # Parity of each tree edge (pred[i], i), looked up among the shared-edge pairs.
    pair_key = np.r_[fa * nf + fb, fb * nf + fa]
    pair_val = np.r_[same_dir, same_dir]
    srt = np.argsort(pair_key)
    pair_key, pair_val = pair_key[srt], pair_val[srt]
    is_root = pred == nf
    q = np.where(is_root, 0, pred) * nf + np.arange(nf)
    pos = np.minimum(np.searchsorted(pair_key, q), max(len(pair_key) - 1, 0))
    flip = np.where(is_root, False, pair_val[pos] if len(pair_key) else False)
    # Pointer jumping: invariant flip[i] = parity from i to ptr[i]; stop once every ptr is a root.
    ptr = np.where(is_root, np.arange(nf), pred)
    while True:
        nxt = ptr[ptr]
        if (nxt == ptr).all():
            break
        flip = flip ^ flip[ptr]
        ptr = nxt
    f[flip] = f[flip][:, ::-1]
    if outward:
        v = np.asarray(vertices, dtype=np.float64)
        t = v[f] - v[np.unique(f)].mean(0)
        vol = np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2]))
        part_vol = np.bincount(label, weights=vol)
        inv = part_vol[label] < 0
        f[inv] = f[inv][:, ::-1]
    return f


