"""Delaunay cells for the solid face stage (``fastmesh.faces.solid``): tetrahedra wound alike, the triangles
between them, and the minimum cut that labels them inside or outside.

The cut's labels are only as good as the tetrahedra's windings: a triangle between two cells is wound outward of
one of them (:func:`cell_faces`), so every tetrahedron must have the same sign of volume, flat ones included
(:func:`tetrahedralise`).  :func:`min_cut` is a plain s-t minimum cut on integer capacities and knows nothing of
geometry: ``fastmesh.faces.plane_cells`` labels its own cells with it too.
"""

from __future__ import annotations

import numpy as np

from .meshops import triangle_areas

# The max-flow capacities are integers: the costs scaled so that the largest is this.
CAPACITY_SCALE = 1 << 20
# The 4 triangles of a tetrahedron, each listed opposite its missing corner (scipy's neighbour order).
_OPPOSITE = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])


def tetrahedralise(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The vertices' Delaunay tetrahedra and their neighbours, all wound alike (positive total volume).

    A flat tetrahedron (four vertices on a plane or a circle, common on an artist's grid) has no reliable sign
    of its own: each takes the winding its neighbours induce (:func:`_coherent`).

    Parameters
    ----------
    vertices : (N, 3) float, not all on one plane

    Returns
    -------
    tets : (K, 4) int64, corners 1, 2, 3 wound counter-clockwise seen from corner 0's far side
    neighbours : (K, 4) int64, the cell across the triangle opposite each corner; -1 is the outside cell
    """
    from scipy.spatial import Delaunay

    v = np.asarray(vertices, dtype=np.float64)
    d = Delaunay(v)
    tets = d.simplices.astype(np.int64)
    nb = d.neighbors.astype(np.int64)
    flip = _coherent(tets, nb)
    if signed_volumes(v, np.where(flip[:, None], tets[:, [1, 0, 2, 3]], tets)).sum() < 0:
        flip = ~flip
    tets[flip] = tets[flip][:, [1, 0, 2, 3]]
    nb[flip] = nb[flip][:, [1, 0, 2, 3]]  # the neighbour opposite a corner moves with it
    return tets, nb


def _coherent(tets: np.ndarray, nb: np.ndarray) -> np.ndarray:
    """(K,) bool: the tetrahedra to turn (swap corners 0 and 1) so that every two neighbours wind their shared
    triangle oppositely, found by propagation over the neighbour graph (a sign per connected part)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(tets)
    tri = _outward(tets)  # (K, 4, 3)
    k, j = np.nonzero((nb >= 0) & (np.arange(n)[:, None] < nb))
    m = nb[k, j]
    jm = np.argmax(nb[m] == k[:, None], axis=1)
    same = _same_winding(tri[k, j], tri[m, jm])  # both wound alike: exactly one of the two must turn
    # Nodes k (kept) and n + k (turned): a pair wound alike joins kept to turned, one wound oppositely alike ones.
    a = np.concatenate([k, k + n])
    b = np.concatenate([np.where(same, m + n, m), np.where(same, m, m + n)])
    graph = coo_matrix((np.ones(len(a), dtype=np.int8), (a, b)), shape=(2 * n, 2 * n))
    label = connected_components(graph, directed=False)[1]
    # A part of the neighbour graph is two components, its tetrahedra kept and turned: the first one stays.
    part = np.minimum(label[:n], label[n:])
    keys, first = np.unique(part, return_index=True)
    root = label[first][np.searchsorted(keys, part)]
    return label[:n] != root


def _outward(tets: np.ndarray) -> np.ndarray:
    """(K, 4, 3) each tetrahedron's triangles, the one opposite corner j at j, wound outward when its volume is
    positive: corners (1, 2, 3) wind away from corner 0 and (0, 2, 3) towards corner 1, so the triangle opposite
    an odd corner turns."""
    tri = tets[:, _OPPOSITE]
    tri[:, 1::2] = tri[:, 1::2][..., [0, 2, 1]]
    return tri


def _same_winding(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(T,) bool: triangles ``x`` and ``y`` (T, 3) of the same three vertices wound alike."""
    rx = np.take_along_axis(x, (np.argmin(x, axis=1)[:, None] + np.arange(3)) % 3, axis=1)
    ry = np.take_along_axis(y, (np.argmin(y, axis=1)[:, None] + np.arange(3)) % 3, axis=1)
    return rx[:, 1] == ry[:, 1]


def signed_volumes(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(K,) signed volumes of tetrahedra ``tets`` (K, 4) of ``vertices`` (N, 3)."""
    p = vertices[tets]
    return np.einsum("ki,ki->k", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) / 6.0


def cell_boundary_areas(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(K,) the total area of each tetrahedron's four triangles (``tets`` (K, 4) of ``vertices`` (N, 3))."""
    return triangle_areas(vertices, _outward(tets).reshape(-1, 3)).reshape(-1, 4).sum(1)


def cell_faces(tets: np.ndarray, neighbours: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each triangle between two cells once: ``(tri (T, 3), a (T,), b (T,))``, cell ``a`` >= 0 on one side and
    ``b`` on the other (-1: the outside cell), ``tri`` wound outward of ``a`` (tets of positive volume)."""
    k = np.repeat(np.arange(len(tets)), 4)
    j = np.tile(np.arange(4), len(tets))
    other = neighbours.reshape(-1)
    once = (other < 0) | (k < other)
    k, j, other = k[once], j[once], other[once]
    return _outward(tets)[k, j], k, other


def min_cut(n_cells: int, inside_cost: np.ndarray, outside_cost: np.ndarray, a: np.ndarray, b: np.ndarray,
            cost: np.ndarray) -> np.ndarray:
    """The labelling of least total cost: a minimum s-t cut (``scipy.sparse.csgraph.maximum_flow``).

    Parameters
    ----------
    n_cells : int
    inside_cost, outside_cost : (K,) float >= 0, what labelling each cell inside or outside costs
    a, b : (T,) int, the cells on either side of each triangle; ``b`` -1 is the outside cell (always outside)
    cost : (T,) float >= 0, what labelling ``a`` and ``b`` apart costs

    Returns
    -------
    (K,) bool, inside
    """
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import breadth_first_order, maximum_flow

    src, snk = n_cells, n_cells + 1
    outside = b < 0
    # A cell next to the outside cell pays the triangle between them when it is inside.
    inside_cost = inside_cost + np.bincount(a[outside], cost[outside], minlength=n_cells)
    a, b, cost = a[~outside], b[~outside], cost[~outside]
    scale = CAPACITY_SCALE / max(float(np.max(inside_cost, initial=0)), float(np.max(outside_cost, initial=0)),
                                 float(np.max(cost, initial=0)), 1e-300)
    cells = np.arange(n_cells)
    rows = np.concatenate([np.full(n_cells, src), cells, a, b])
    cols = np.concatenate([cells, np.full(n_cells, snk), b, a])
    # Source side = inside: the edge from the source is cut when a cell is outside, the one to the sink when inside.
    cap = np.concatenate([outside_cost, inside_cost, cost, cost]) * scale
    cap = np.ceil(cap).astype(np.int32)
    keep = cap > 0
    graph = csr_matrix((cap[keep], (rows[keep], cols[keep])), shape=(n_cells + 2, n_cells + 2))
    graph.sum_duplicates()
    flow = maximum_flow(graph, src, snk).flow
    residual = (graph - flow).tocsr()
    residual.data = np.where(residual.data > 0, 1, 0).astype(np.int32)
    residual.eliminate_zeros()
    reached = breadth_first_order(residual, src, directed=True, return_predecessors=False)
    inside = np.zeros(n_cells + 2, dtype=bool)
    inside[reached] = True
    return inside[:n_cells]
