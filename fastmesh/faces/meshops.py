"""Small operations on triangle meshes that the face stage, the measures and the tokenizers' tests share: a
mesh's sides and edges, the faces on each edge, areas, welding, unused vertices, the fans around each vertex,
the pieces joined edge to edge, the distance from points to a mesh and the nearest point of a triangle.  Faces
are (F, 3) int arrays, vertices (N, 3) float arrays."""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree


def face_sides(faces: np.ndarray) -> np.ndarray:
    """(3F, 2) int64 the sides of each face as it winds: all (0, 1) sides, then all (1, 2), then all (2, 0);
    side ``i * F + k`` is side i of face k."""
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    return np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3) normals of ``vertices[faces]`` ((F, 3) int), each as long as twice its face's area (unnormalised)."""
    t = np.asarray(vertices, dtype=np.float64)[faces]
    return np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])


def triangle_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F,) areas of ``vertices[faces]`` in squared input units."""
    return 0.5 * np.linalg.norm(face_normals(vertices, faces), axis=1)


def remove_unreferenced(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Drop vertices no face uses.

    Returns
    -------
    vertices : (M, 3), faces : (F, 3) remapped, kept : (M,) int64 original index of each kept vertex.
    """
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    used = np.zeros(len(vertices), dtype=bool)
    used[f.ravel()] = True
    remap = np.cumsum(used) - 1
    return np.asarray(vertices)[used], remap[f], np.flatnonzero(used)


def edges_from_faces(faces: np.ndarray) -> np.ndarray:
    """(F, 3) triangles -> (E, 2) int64 unique undirected edges, each (i, j) with i < j, sorted."""
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    e = face_sides(f)
    return normalize_edges(e)


def normalize_edges(edges: np.ndarray) -> np.ndarray:
    """(E, 2) int pairs -> unique (i, j) rows with i < j, self-loops dropped, sorted."""
    e = np.sort(np.asarray(edges, dtype=np.int64).reshape(-1, 2), axis=1)
    e = e[e[:, 0] != e[:, 1]]
    return np.unique(e, axis=0) if len(e) else e


def edge_face_counts(faces: np.ndarray) -> np.ndarray:
    """How many faces use each undirected edge.

    Parameters
    ----------
    faces : (F, 3) int

    Returns
    -------
    (E,) int64 : one count per distinct edge (order unspecified).
    """
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    e = np.sort(face_sides(f), axis=1)
    if len(e) == 0:
        return np.zeros(0, dtype=np.int64)
    return np.unique(e, axis=0, return_counts=True)[1].astype(np.int64)


def crowded_edges(faces: np.ndarray) -> np.ndarray:
    """(C, 2) the edges (sorted ends) in more than two of ``faces`` (F, 3)."""
    keys, counts = np.unique(np.sort(face_sides(faces), axis=1), axis=0, return_counts=True)
    return keys[counts > 2]


def side_counts(faces: np.ndarray) -> np.ndarray:
    """(3F,) int64, per side of :func:`face_sides`: how many of ``faces`` (F, 3) use its edge."""
    sides = np.sort(face_sides(faces), axis=1)
    if len(sides) == 0:
        return np.zeros(0, dtype=np.int64)
    _, inverse, count = np.unique(sides, axis=0, return_inverse=True, return_counts=True)
    return count[inverse.reshape(-1)]


def open_sides(faces: np.ndarray) -> np.ndarray:
    """(3F,) bool, per side of :func:`face_sides`: its edge is in no other face (an open edge)."""
    return side_counts(faces) == 1


def wound_alike(faces: np.ndarray) -> bool:
    """Whether no edge of ``faces`` (F, 3) has more than two faces and no two faces run one edge the same way (an
    edge-manifold surface, closed or open, consistently wound)."""
    sides = face_sides(faces)
    return len(np.unique(sides, axis=0)) == len(sides) and int(edge_face_counts(faces).max(initial=0)) <= 2


def corner_fans(faces: np.ndarray) -> np.ndarray:
    """(3F,) the fan of each face corner around its vertex: corners of one vertex share a label exactly when
    their faces are joined edge to edge around it.  Corner i of face k is entry ``i * F + k``.

    Parameters
    ----------
    faces : (F, 3) int
    """
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    # Each corner (v; x, y) joins the spokes v-x and v-y of v's fan: a vertex with one fan has one
    # connected set of spokes.
    corners = np.concatenate([f, f[:, [1, 2, 0]], f[:, [2, 0, 1]]])
    spokes = np.concatenate([corners[:, [0, 1]], corners[:, [0, 2]]])
    keys, ids = np.unique(spokes, axis=0, return_inverse=True)
    ids = ids.reshape(-1)
    half = len(corners)
    graph = coo_matrix((np.ones(half, dtype=np.int8), (ids[:half], ids[half:])), shape=(len(keys), len(keys)))
    return connected_components(graph, directed=False)[1][ids[:half]]


def piece_labels(faces: np.ndarray) -> np.ndarray:
    """(F,) the piece of each face (:func:`count_pieces`), labels 0 .. pieces - 1."""
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(f) == 0:
        return np.zeros(0, dtype=np.int64)
    e = np.sort(np.stack([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], axis=1), axis=2).reshape(-1, 2)
    edge = np.unique(e, axis=0, return_inverse=True)[1].reshape(-1)
    # Faces and edges as the nodes of one graph, each face joined to its three edges.
    n = len(f) + int(edge.max()) + 1
    graph = coo_matrix((np.ones(len(edge), dtype=np.int8), (np.repeat(np.arange(len(f)), 3), len(f) + edge)),
                       shape=(n, n))
    return connected_components(graph, directed=False)[1][:len(f)].astype(np.int64)


def weld(vertices: np.ndarray, faces: np.ndarray, tol: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """A mesh's vertices within ``tol`` of its longest side of each other made one, and the faces that
    collapse dropped: files split vertices along UV seams and hard edges, which are not openings.

    Parameters
    ----------
    vertices : (N, 3) float
    faces : (F, 3) int

    Returns
    -------
    vertices : (M, 3) float64, the first of each welded group
    faces : (F', 3) int64
    """
    v, f = welded_in_place(vertices, faces, tol)
    return v, f[distinct_corners(f)]


def distinct_corners(faces: np.ndarray) -> np.ndarray:
    """(F,) bool, the ``faces`` (F, 3) whose three corners are three vertices (not collapsed by a weld or a merge)."""
    f = np.asarray(faces).reshape(-1, 3)
    return (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])


def welded_in_place(vertices: np.ndarray, faces: np.ndarray, tol: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """:func:`weld`'s vertices (M, 3), and every one of ``faces`` (F, 3) in its place on them, collapsed or not."""
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(v) == 0:
        return v, f
    extent = float(np.ptp(v, axis=0).max()) or 1.0
    _, first, inverse = np.unique(np.round((v - v.min(0)) / (extent * tol)), axis=0, return_index=True,
                                  return_inverse=True)
    return v[first], inverse.reshape(-1)[f]


def welded_fins(vertices: np.ndarray, faces: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    """(F,) bool, the ``faces`` (F, 3) with a side in more than two faces once the ``vertices`` (N, 3) within
    ``tol`` of the longest side of each other are one (as :func:`weld` makes them, and an exported file's reader
    may): pieces that touch along a side without sharing its vertices make such fins."""
    if len(faces) == 0:
        return np.zeros(0, dtype=bool)
    one = welded_in_place(vertices, faces, tol)[1]
    live = distinct_corners(one)
    sides = np.sort(face_sides(one), axis=1)
    _, inverse, count = np.unique(sides, axis=0, return_inverse=True, return_counts=True)
    live_count = np.bincount(inverse.reshape(-1), weights=np.tile(live, 3).astype(float), minlength=len(count))
    return live & (live_count[inverse.reshape(-1)] > 2).reshape(3, -1).any(0)


def distance_to_triangles(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                          chunk: int = 1 << 20) -> np.ndarray:
    """Exact Euclidean distance from each point to the nearest triangle of a mesh.

    The distance to the nearest mesh vertex bounds each point's answer from above, so only the
    triangles whose bounding box lies nearer than that bound are measured exactly.

    Parameters
    ----------
    points : (N, 3) float
    vertices : (V, 3) float
    faces : (F, 3) int, F >= 1
    chunk : int
        Point-triangle pairs tested per vectorised step (bounds the memory).

    Returns
    -------
    (N,) float64 distances.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    vv = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(f) == 0:
        raise ValueError("distance_to_triangles needs at least one face")
    tri = vv[f]  # (F, 3, 3)
    best, _ = cKDTree(vv[np.unique(f)]).query(p)
    lo, hi = tri.min(1), tri.max(1)  # (F, 3) bounding boxes
    rows = max(1, chunk // len(f))
    for s in range(0, len(p), rows):
        q = p[s:s + rows]
        gap = np.maximum(np.maximum(lo[None] - q[:, None], q[:, None] - hi[None]), 0.0)
        pi, fi = np.nonzero((gap ** 2).sum(-1) < best[s:s + rows, None] ** 2)
        if len(pi):
            d = point_triangle_distance(q[pi], tri[fi])
            np.minimum.at(best, s + pi, d)
    return best


def point_triangle_distance(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """(K, 3) points and (K, 3, 3) triangles -> (K,) distances, pair by pair.

    Inside the triangle's prism the distance is the one to its plane; outside it (and for a
    degenerate triangle) the nearest point lies on one of the three edges.
    """
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    n = np.cross(b - a, c - a)
    nn = (n * n).sum(-1)
    inside = nn > 0
    for x, y in ((a, b), (b, c), (c, a)):
        inside &= (np.cross(y - x, p - x) * n).sum(-1) >= 0
    plane = np.abs(((p - a) * n).sum(-1)) / np.sqrt(np.where(nn > 0, nn, 1.0))
    edge = np.full(len(p), np.inf)
    for x, y in ((a, b), (b, c), (c, a)):
        e = y - x
        t = np.clip(((p - x) * e).sum(-1) / np.maximum((e * e).sum(-1), 1e-300), 0.0, 1.0)
        edge = np.minimum(edge, np.linalg.norm(p - (x + t[:, None] * e), axis=-1))
    return np.where(inside, plane, edge)


def closest_on_triangles(points: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """(N, 3) barycentric coordinates of the point of each triangle ``tri`` (N, 3, 3) nearest ``points``
    (N, 3): the projection onto its plane where that lies inside, else the nearest point of its edges."""
    e1, e2, w = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], points - tri[:, 0]

    def dot(x, y):
        return np.einsum("nd,nd->n", x, y)

    d00, d01, d11, d20, d21 = dot(e1, e1), dot(e1, e2), dot(e2, e2), dot(w, e1), dot(w, e2)
    denom = d00 * d11 - d01 * d01
    denom = np.where(denom > 0, denom, 1e-300)
    b1, b2 = (d11 * d20 - d01 * d21) / denom, (d00 * d21 - d01 * d20) / denom
    bary = np.stack([1.0 - b1 - b2, b1, b2], axis=1)  # of the projection onto the plane
    out = np.flatnonzero(np.any(bary < 0, axis=1))
    if len(out):
        p, best, best_d = points[out], None, None
        for k in range(3):  # the edge from corner k to corner k + 1
            s, e = tri[out, k], tri[out, (k + 1) % 3]
            d = e - s
            t = np.clip(np.sum((p - s) * d, axis=1) / np.maximum(np.sum(d * d, axis=1), 1e-300), 0.0, 1.0)
            dist = np.sum((s + t[:, None] * d - p) ** 2, axis=1)
            cand = np.zeros((len(out), 3))
            cand[:, k], cand[:, (k + 1) % 3] = 1.0 - t, t
            if best is None:
                best, best_d = cand, dist
            else:
                closer = dist < best_d
                best[closer], best_d[closer] = cand[closer], dist[closer]
        bary[out] = best
    return bary
