"""Defects a renderer or an editor shows and distances miss (../shared/EVAL.md, "What a renderer shows").

    misoriented_edges     interior edges (two faces) whose two faces run them the same way
    misoriented_area      per edge-connected piece, the area wound against the rest of its piece (the smaller
                          of its two orientation classes; for a piece no turning makes agree, of the classes
                          along a spanning tree that crosses as few disagreeing edges as it can), summed and
                          divided by the mesh's area, 0..0.5
    self_intersections    pairs of faces sharing no vertex that cross each other
    unwelded_vertices     vertices that coincide with another vertex of a different index

Winding and crossings are measured on the mesh with coincident vertices welded (``meshops.weld``): files
split vertices along seams, which is neither an opening nor a crossing; the split itself is what
``unwelded_vertices`` counts.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .meshops import distinct_corners, face_sides, remove_unreferenced, triangle_areas, weld, welded_in_place

TOUCH = 1e-7  # overlaps thinner than this share of the longest side are touching, not crossing
PAIR_CHUNK = 50_000  # face pairs tested per vectorised step (~2 kB each)


def _interior_pairs(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Faces ``a``, ``b`` (K,) across each edge used by exactly two faces, and ``same`` (K,) bool: both
    run the edge the same way."""
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    sides = face_sides(f)
    owner = np.tile(np.arange(len(f)), 3)
    key, inverse, counts = np.unique(np.sort(sides, axis=1), axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    two = np.flatnonzero(counts[inverse] == 2)
    two = two[np.argsort(inverse[two], kind="stable")]
    first, second = two[0::2], two[1::2]
    same = sides[first, 0] == sides[second, 0]
    return owner[first], owner[second], same


def winding(vertices: np.ndarray, faces: np.ndarray) -> dict:
    """Faces wound against their neighbours.

    Parameters
    ----------
    vertices : (V, 3) float
    faces : (F, 3) int

    Returns
    -------
    dict : misoriented_edges (int), misoriented_area (float, share of the area, 0..0.5).
    """
    v, f = weld(vertices, faces)
    if len(f) == 0:
        return {"misoriented_edges": 0, "misoriented_area": 0.0}
    a, b, same, piece, turned, _ = _classes(f)
    area = triangle_areas(v, f)
    one = np.bincount(piece, weights=np.where(turned, 0.0, area), minlength=2 * len(f))
    other = np.bincount(piece, weights=np.where(turned, area, 0.0), minlength=2 * len(f))
    wrong = float(np.minimum(one, other).sum())
    return {"misoriented_edges": int(same.sum()), "misoriented_area": wrong / max(float(area.sum()), 1e-300)}


def unorientable_faces(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F,) bool, the ``faces`` (F, 3) along an edge that no turning of faces makes agree (welded as
    :func:`winding` welds): in a piece twisted like a Moebius band (a strip of faces turned half over and
    joined), the edges still wound the same way by both their faces once the piece is turned along
    :func:`_tree_classes`' tree.  A renderer shows the back of one side of such an edge whichever way the piece is
    turned.  A closed piece folded through itself is wound one way and has none (its faces cross instead)."""
    bad = np.zeros(len(faces), dtype=bool)
    v, f = welded_in_place(vertices, faces)
    live = np.flatnonzero(distinct_corners(f))
    if len(live) == 0:
        return bad
    a, b, same, piece, turned, knotted = _classes(f[live])
    stuck = (same ^ (turned[a] != turned[b])) & np.isin(piece[a], knotted)
    bad[live[np.r_[a[stuck], b[stuck]]]] = True
    return bad


def _classes(f: np.ndarray) -> tuple:
    """Each face's orientation class on a mesh's ``f`` (F, 3): the faces ``a``, ``b`` (K,) across each edge of two
    faces and ``same`` (K,) whether both run it the same way (:func:`_interior_pairs`); ``piece`` (F,) an id of each
    face's edge-connected piece; ``turned`` (F,) bool, the faces to turn for each piece to agree (for the
    ``knotted`` pieces, which no turning makes agree, along :func:`_tree_classes`' tree)."""
    a, b, same = _interior_pairs(f)
    # Orientation classes on the double cover: node (face, +) is face, (face, -) is face + F.  Agreeing
    # neighbours join + to + and - to -, disagreeing ones + to -; in an orientable piece the faces whose +
    # node lies with the piece's first face's + node are one class, the rest the other.
    n = len(f)
    rows = np.concatenate([a, a + n])
    cols = np.concatenate([np.where(same, b + n, b), np.where(same, b, b + n)])
    graph = coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(2 * n, 2 * n))
    label = connected_components(graph, directed=False)[1]
    plus, minus = label[:n], label[n:]
    piece = np.minimum(plus, minus)  # the same for both classes of a piece
    turned = plus != piece  # (F,) the class each face is in
    knotted = np.unique(piece[plus == minus])  # pieces no turning makes agree (a fold, a Moebius band)
    if len(knotted):
        turned = _tree_classes(a, b, same, piece, knotted, turned)
    return a, b, same, piece, turned, knotted


def _tree_classes(a: np.ndarray, b: np.ndarray, same: np.ndarray, piece: np.ndarray, knotted: np.ndarray,
                  turned: np.ndarray) -> np.ndarray:
    """``turned`` with the faces of the ``knotted`` pieces put in classes along a spanning tree of each piece
    that crosses as few disagreeing edges as it can (a minimum spanning tree, agreeing edges cheaper): a face
    is turned against its parent where both run their shared edge the same way.  A band turned half a turn
    then reads no area against the rest, a patch wound the other way on it some area (where two turnings
    leave as many edges disagreeing, the tree picks one: the area is then an upper bound)."""
    from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree

    n = len(piece)
    # One entry per pair of faces (two faces sharing two edges would add up): 1 agree, 2 disagree.
    _, first = np.unique(np.sort(np.c_[a, b], axis=1), axis=0, return_index=True)
    a, b, value = a[first], b[first], same[first].astype(np.int8) + 1
    flip = minimum_spanning_tree(coo_matrix((value, (a, b)), shape=(n, n)).tocsr())
    flip = (flip + flip.T).tocsr()
    out = turned.copy()
    for p in knotted:
        root = int(np.flatnonzero(piece == p)[0])
        order, parent = breadth_first_order(flip, root, directed=False)
        against = (np.asarray(flip[parent[order[1:]], order[1:]]).ravel() > 1).tolist()
        side = {int(root): False}
        for node, up, x in zip(order[1:].tolist(), parent[order[1:]].tolist(), against, strict=True):
            side[node] = side[up] ^ x  # parents come first in breadth-first order
        out[list(side)] = list(side.values())
    return out


def unwelded_vertices(vertices: np.ndarray, faces: np.ndarray, tol: float = 1e-6) -> int:
    """Referenced vertices of (V, 3) ``vertices`` within ``tol`` of the longest side of another one
    (``meshops.weld``'s rule), counted beyond the first of each group."""
    used, f, _ = remove_unreferenced(np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64))
    return int(len(used) - len(weld(used, f, tol)[0]))


def _candidate_pairs(tri: np.ndarray) -> np.ndarray:
    """(K, 2) face pairs i < j whose bounding spheres about the centroids overlap.

    Faces are binned by radius (powers of two) so that one huge face does not widen every query.
    """
    centre = tri.mean(1)
    radius = np.linalg.norm(tri - centre[:, None], axis=2).max(1)
    top = max(float(radius.max()), 1e-300)
    level = np.clip(np.floor(np.log2(np.maximum(radius, 1e-300) / top)), -16, 0).astype(np.int64)
    groups = [np.flatnonzero(level == k) for k in np.unique(level)]
    trees = [cKDTree(centre[g]) for g in groups]
    reach = [float(radius[g].max()) for g in groups]
    out = []
    for i, (gi, ti) in enumerate(zip(groups, trees, strict=True)):
        for j in range(i, len(groups)):
            r = reach[i] + reach[j]
            if i == j:
                p = ti.query_pairs(r, output_type="ndarray")
            else:
                m = ti.sparse_distance_matrix(trees[j], r, output_type="ndarray")
                p = np.stack([m["i"], m["j"]], axis=1)
            if len(p):
                out.append(np.stack([gi[p[:, 0]], groups[j][p[:, 1]]], axis=1))
    pairs = np.concatenate(out) if out else np.zeros((0, 2), dtype=np.int64)
    return np.sort(pairs, axis=1)


def triangles_cross(t1: np.ndarray, t2: np.ndarray, tol: float) -> np.ndarray:
    """(K,) bool: triangles ``t1`` and ``t2`` (K, 3, 3) reach more than ``tol`` into each other along every axis of
    the separating-axis test (both normals, the nine edge-edge crosses and each triangle's in-plane edge
    normals, for coplanar pairs).  Axes of near-zero length (parallel edges) are skipped."""
    e1 = t1[:, [1, 2, 0]] - t1
    e2 = t2[:, [1, 2, 0]] - t2
    n1 = np.cross(e1[:, 0], e1[:, 1])
    n2 = np.cross(e2[:, 0], e2[:, 1])
    axes = [n1[:, None], n2[:, None], np.cross(e1[:, :, None], e2[:, None, :]).reshape(-1, 9, 3),
            np.cross(n1[:, None], e1), np.cross(n2[:, None], e2)]
    axes = np.concatenate(axes, axis=1)  # (K, 17, 3)
    length = np.linalg.norm(axes, axis=2)
    scale = np.maximum(np.ptp(np.concatenate([t1, t2], axis=1), axis=1).max(1), 1e-300)
    valid = length > 1e-12 * scale[:, None] ** 2
    axes = axes / np.where(valid, length, 1.0)[:, :, None]
    p1 = np.einsum("kad,kvd->kav", axes, t1)
    p2 = np.einsum("kad,kvd->kav", axes, t2)
    # Separated along an axis where one interval ends within ``tol`` of where the other begins (a flat
    # triangle's interval along its own normal is a point: interval overlap would always read 0 there).
    gap = np.minimum(p1.max(2) - p2.min(2), p2.max(2) - p1.min(2))
    return ~np.any(valid & (gap <= tol), axis=1)


def self_intersections(vertices: np.ndarray, faces: np.ndarray) -> int:
    """Pairs of faces of a mesh sharing no vertex (after welding) that cross each other.

    A broad phase keeps pairs whose bounding spheres and boxes overlap; the separating-axis test
    (:func:`triangles_cross`) decides each, touching within ``TOUCH`` of the longest side not counting.
    """
    v, f = weld(vertices, faces)
    if len(f) < 2:
        return 0
    tri = v[f]
    pairs = _candidate_pairs(tri)
    lo, hi = tri.min(1), tri.max(1)
    tol = TOUCH * (float(np.ptp(v[np.unique(f)], axis=0).max()) or 1.0)
    keep = np.all((lo[pairs[:, 0]] <= hi[pairs[:, 1]] + tol) & (lo[pairs[:, 1]] <= hi[pairs[:, 0]] + tol), axis=1)
    pairs = pairs[keep]
    shared = (f[pairs[:, 0]][:, :, None] == f[pairs[:, 1]][:, None, :]).any(axis=(1, 2))
    pairs = pairs[~shared]
    count = 0
    for s in range(0, len(pairs), PAIR_CHUNK):
        p = pairs[s:s + PAIR_CHUNK]
        count += int(triangles_cross(tri[p[:, 0]], tri[p[:, 1]], tol).sum())
    return count


def defects(vertices: np.ndarray, faces: np.ndarray) -> dict:
    """:func:`winding`, :func:`self_intersections` and :func:`unwelded_vertices` of one mesh, as one dict."""
    return {**winding(vertices, faces), "self_intersections": self_intersections(vertices, faces),
            "unwelded_vertices": unwelded_vertices(vertices, faces)}
