"""Corners of a mesh input: the points where three or more of its planes meet.

A mesh shows for free what a point cloud hides: its creases.  A dense mesh (a scan, a remesh, a sculpt) keeps a
sharp crease as a line of edges whose two faces turn by more than ``CREASE_DEGREES``; where three such lines
meet, or one turns or ends, an artist's mesh has a vertex.  :func:`mesh_corners` finds those places and puts
each corner where the planes of the faces around it meet (the least-squares point of their quadric, as
``fitting.fit_to_planes`` does for samples), keeping only those the planes fix in all three directions.

The vertex stage reads them as evidence (``pipeline.candidate``: their cells' log-odds raised), so the decoder
emits a vertex there and the fit puts it on the corner.  On the 60 held-out mesh inputs 95 % of the corners
found lie within one cell of an artist's vertex, and they hold 46 % of the artist's vertices (docs/results.md).
"""

from __future__ import annotations

import numpy as np

from ..tokenizer.grid import CELL

CREASE_DEGREES = 20.0  # an edge whose faces turn by more is a crease
TURN_DEGREES = 30.0  # a crease line that turns by more at a vertex has a corner there
RADIUS_CELLS = 1.5  # the faces around a corner: those of the vertices within this many cells
RANK_REL = 0.02  # the planes fix a third direction where its eigenvalue is at least this share of the largest
MERGE_CELLS = 0.5  # corners closer than this many cells are one
# A mesh whose seeds are more than MAX_SEED_SHARE of its vertices (and more than FEW_SEEDS: in a low-poly mesh every
# vertex is one) is creased nearly everywhere: noise, a scan's facets (a box remeshed and moved by noise of a
# quarter cell: 76 %); its "corners" are noise.  The 60 held-out mesh inputs have at most 15 % (median 2 %) and at
# most 1,264 seeds.  Past MAX_SEEDS reading them would cost seconds.
MAX_SEED_SHARE = 0.3
FEW_SEEDS = 1000
MAX_SEEDS = 20_000
SEED_CHUNK = 2048  # seeds whose faces are gathered at once: bounds the memory on a dense mesh


def edge_turns(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The edges shared by exactly two faces and how their faces' planes turn there.

    Parameters
    ----------
    vertices : (N, 3) float
    faces : (F, 3) int, welded (a split seam has no two faces on an edge)

    Returns
    -------
    edges : (E, 2) int64, sorted pairs
    cos : (E,) float64, the cosine between the two faces' unit normals as wound (-1: folded back)
    """
    v, f = np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n /= np.maximum(np.linalg.norm(n, axis=1), 1e-300)[:, None]
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    owner = np.tile(np.arange(len(f)), 3)
    order = np.argsort(e[:, 0] * len(v) + e[:, 1], kind="stable")  # one int64 key sorts faster than two
    e, owner = e[order], owner[order]
    same = (e[1:] == e[:-1]).all(1)
    # Exactly two faces: the pair is neither continued nor preceded by a third use of the edge (a non-manifold
    # edge has no one turn).
    first = np.flatnonzero(same & np.r_[True, ~same[:-1]] & np.r_[~same[1:], True])
    return e[first], np.einsum("ij,ij->i", n[owner[first]], n[owner[first + 1]])


def crease_edges(vertices: np.ndarray, faces: np.ndarray, degrees: float = CREASE_DEGREES) -> np.ndarray:
    """(E, 2) int64 edges shared by exactly two faces (F, 3) whose planes turn by more than ``degrees`` (and less
    than 180 minus it: the normals' signs are not read, so a file whose windings flip between two faces of a
    flat region has no crease there)."""
    edges, cos = edge_turns(vertices, faces)
    return edges[np.abs(cos) < np.cos(np.radians(degrees))]


def corner_seeds(vertices: np.ndarray, creases: np.ndarray, turn_degrees: float = TURN_DEGREES) -> np.ndarray:
    """(K,) vertices where crease lines meet (three or more crease edges), end (one), or turn by more than
    ``turn_degrees`` (two)."""
    v = np.asarray(vertices, dtype=np.float64)
    degree = np.bincount(creases.ravel(), minlength=len(v))
    seeds = [np.flatnonzero((degree >= 3) | (degree == 1))]
    two = degree == 2
    ends = creases[two[creases[:, 0]] | two[creases[:, 1]]]
    if len(ends):
        # Each degree-2 vertex's two neighbours along its line: the crease edges at it, sorted by that vertex.
        at = np.concatenate([ends, ends[:, ::-1]])
        at = at[two[at[:, 0]]]
        at = at[np.argsort(at[:, 0], kind="stable")]
        mid, a, b = at[0::2, 0], at[0::2, 1], at[1::2, 1]
        d1, d2 = v[a] - v[mid], v[b] - v[mid]
        cos = np.einsum("ij,ij->i", d1, d2) / np.maximum(
            np.linalg.norm(d1, axis=1) * np.linalg.norm(d2, axis=1), 1e-300)
        seeds.append(mid[cos > -np.cos(np.radians(turn_degrees))])  # straight on: cos = -1
    return np.unique(np.concatenate(seeds))


def mesh_corners(vertices: np.ndarray, faces: np.ndarray, radius: float = RADIUS_CELLS * CELL,
                 rel: float = RANK_REL, merge: float = MERGE_CELLS * CELL) -> np.ndarray:
    """The corners of a mesh: where the planes around each of its :func:`corner_seeds` meet.

    Parameters
    ----------
    vertices : (N, 3) float
        In the unit cube (``radius`` and ``merge`` are in its units); welded, so that creases have two faces.
    faces : (F, 3) int
    radius : float
        A seed's planes are the faces of the vertices within this distance; a corner farther than this
        from its seed is not one.
    rel : float
        The planes must fix the third direction by at least this share of the first (a crease fixes two).
    merge : float
        Corners closer than this become one, at their mean.

    Returns
    -------
    (K, 3) float64
    """
    v, f = np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64)
    if len(f) == 0:
        return np.zeros((0, 3))
    seeds = corner_seeds(v, crease_edges(v, f))
    noise = len(seeds) > max(FEW_SEEDS, MAX_SEED_SHARE * len(v))
    if noise or not 0 < len(seeds) <= MAX_SEEDS:
        return np.zeros((0, 3))
    from scipy.spatial import cKDTree

    tree, incidence = cKDTree(v), _incidence(f, len(v))
    quad, rhs = np.zeros((len(seeds), 3, 3)), np.zeros((len(seeds), 3))
    for start in range(0, len(seeds), SEED_CHUNK):
        part = seeds[start:start + SEED_CHUNK]
        near = tree.query_ball_point(v[part], radius)
        quad[start:start + len(part)], rhs[start:start + len(part)] = _planes_near(v, f, part, near, incidence)
    lam = np.linalg.eigvalsh(quad)
    ok = lam[:, 0] >= rel * np.maximum(lam[:, -1], 1e-300)
    if not ok.any():
        return np.zeros((0, 3))
    at = np.linalg.solve(quad[ok], rhs[ok][:, :, None])[:, :, 0]
    at = at[np.linalg.norm(at - v[seeds[ok]], axis=1) <= radius]
    return _merged(at, merge)


def _planes_near(v: np.ndarray, f: np.ndarray, seeds: np.ndarray, near: list, incidence: tuple
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Per seed the quadric (3, 3) and right-hand side (3,) of the planes of the faces of its ``near`` vertices
    (each face once), each weighted by its area: sum a n n^T and sum a n (n . p).  ``incidence``: the faces of
    each vertex as one list and its offsets (:func:`_incidence`)."""
    by_vertex, start = incidence
    row = np.repeat(np.arange(len(seeds)), [len(nb) for nb in near])
    vert = np.concatenate([np.asarray(nb, dtype=np.int64) for nb in near])
    count = start[vert + 1] - start[vert]
    pos = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count) + np.repeat(start[vert], count)
    key = np.unique(np.repeat(row, count) * len(f) + by_vertex[pos] // 3)
    owner, around = key // len(f), key % len(f)
    faces, which = np.unique(around, return_inverse=True)  # only these: a dense mesh has millions elsewhere
    t = v[f[faces]]
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])  # length: twice the area, the plane's weight
    area = np.linalg.norm(n, axis=1)
    unit = n / np.maximum(area, 1e-300)[:, None]
    quad, rhs = np.zeros((len(seeds), 3, 3)), np.zeros((len(seeds), 3))
    np.add.at(quad, owner, (unit[:, :, None] * unit[:, None, :] * area[:, None, None])[which])
    np.add.at(rhs, owner, (unit * (np.einsum("ij,ij->i", unit, t[:, 0]) * area)[:, None])[which])
    return quad, rhs


def _incidence(f: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """The faces of each vertex as one list of corner slots (slot // 3 is the face) sorted by vertex, and the
    offsets of each vertex's run in it ((n_vertices + 1,))."""
    by_vertex = np.argsort(f.ravel(), kind="stable")
    return by_vertex, np.searchsorted(f.ravel()[by_vertex], np.arange(n_vertices + 1))


def _merged(points: np.ndarray, tol: float) -> np.ndarray:
    """(K, 3) means of the groups of ``points`` (M, 3) linked by distances under ``tol``."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    if len(points) < 2:
        return points
    pairs = cKDTree(points).query_pairs(tol, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(points),) * 2)
    k, label = connected_components(graph, directed=False)
    sums = np.zeros((k, 3))
    np.add.at(sums, label, points)
    return sums / np.bincount(label, minlength=k)[:, None]
