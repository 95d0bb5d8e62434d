"""The cliques of a predicted edge graph: every triangle (3-clique) and every 4-clique, enumerated vectorised.

Vertices are ranked by degree, every edge points from lower to higher rank, and a triangle is found once as a
wedge ``x -> y -> z`` closed by the edge ``x -> z`` (with degree ranking each vertex has at most sqrt(2E)
out-neighbours, so the wedges stay few even for dense predictions).
"""

from __future__ import annotations

import numpy as np

from .meshops import normalize_edges

# Wedges expanded per vectorised chunk: bounds memory at ~100 MB for any adjacency.
_CHUNK = 2_000_000


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
