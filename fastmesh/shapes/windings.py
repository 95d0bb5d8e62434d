"""Faces wound alike across the edges they share: each face's flip fixed along a spanning forest of the face graph.

``faces.orient`` turns a generated result's pieces with these flips, then outward by their signed volume; the open
planes path (``open_planar``) turns a rebuilt surface's pieces with them, then the way most of its area was wound
by its planes' points (:func:`agreeing`): a scan's normals, whose signs its points set only where they enclose a
volume, may wind one plane of a sheet against the others.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import breadth_first_order, connected_components


def face_pairs(f: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pairs of faces (fa, fb: (P,) int64) on each edge of exactly two distinct faces of ``f`` (F, 3), and
    (P,) bool whether they run the edge the same way (then one of the two must flip)."""
    he = np.stack([f, np.roll(f, -1, axis=1)], axis=2).reshape(-1, 2)  # half-edges (3F, 2), face = index // 3
    key = np.sort(he, axis=1) @ np.array([n_vertices, 1])
    order = np.argsort(key, kind="stable")
    ks = key[order]
    start = np.flatnonzero(np.r_[True, ks[1:] != ks[:-1]])
    count = np.diff(np.r_[start, len(ks)])
    two = start[count == 2]
    h1, h2 = order[two], order[two + 1]
    fa, fb = h1 // 3, h2 // 3
    same_dir = he[h1, 0] == he[h2, 0]  # equal directions: one of the two must flip
    ok = fa != fb
    return fa[ok], fb[ok], same_dir[ok]


def winding_flips(fa: np.ndarray, fb: np.ndarray, same_dir: np.ndarray, nf: int) -> tuple[np.ndarray, np.ndarray]:
    """(nf,) bool which faces flip so that every pair agrees with its part's root where a spanning forest of
    the pairs reaches, and (nf,) the part (connected component of the face graph) of each face.

    One breadth-first traversal from a virtual root linked to every part; the flips accumulate along the tree
    by pointer jumping (vectorised, O(F log depth)).  Edges with more than two faces do not constrain winding."""
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
    return flip, label


def agreeing(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``faces`` wound alike across every edge of two faces, each piece the way more than half its area was wound.

    Parameters
    ----------
    vertices : (V, 3) float
    faces : (F, 3) int

    Returns
    -------
    (F, 3) int64 faces, same order, some reversed (none where they were wound alike already and no piece has more
    than half its area wound against the rest).
    """
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3).copy()
    if len(f) == 0:
        return f
    flip, label = winding_flips(*face_pairs(f, len(vertices)), len(f))
    v = np.asarray(vertices, dtype=np.float64)
    area = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    pieces = int(label.max()) + 1
    against = np.bincount(label, area * flip, pieces) > 0.5 * np.bincount(label, area, pieces)
    flip ^= against[label]
    f[flip] = f[flip][:, ::-1]
    return f
