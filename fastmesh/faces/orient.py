"""Consistent, outward windings: each face's flip fixed along a spanning forest of the face graph; open pieces
turned to face the input (:func:`face_input`); a mesh's pieces stored inside out turned (:func:`outward_pieces`)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .meshops import open_sides, piece_labels, side_counts

# A face's side is read from this many input samples nearest its centroid (:func:`sides_asked`)...
SIDE_SAMPLES = 8
# ... each of which says it where its normal lies within acos(this) of the face's normal, either way.
SIDE_COS = 0.3
# A piece with an open edge is a sheet, sided by the input rather than by its signed volume, where that volume is
# under this share of its area^(3/2): random wavy sheets read 0.0000, the open results of held-out inputs 0.005 to
# 0.06 (a sphere's whole surface 0.094), which their signed volume sides rightly.
SHEET_VOLUME = 0.002


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
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3).copy()
    if len(f) == 0:
        return f
    fa, fb, same_dir = _face_pairs(f, len(vertices))
    flip, label = _flips(fa, fb, same_dir, len(f))
    f[flip] = f[flip][:, ::-1]
    if outward:
        v = np.asarray(vertices, dtype=np.float64)
        inv = _volumes(v, f, label, v[np.unique(f)].mean(0))[label] < 0
        f[inv] = f[inv][:, ::-1]
    return f


def outward_pieces(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``faces`` with each piece wound one way whose signed volume about its centroid is negative reversed: a mesh
    stored inside out (as many game formats keep theirs) shows a renderer the backs of its faces.  Exact for a
    closed piece, and read as :func:`orient_faces` reads it for an open one that encloses a volume (a body open at
    the neck); a sheet (``SHEET_VOLUME``) and a piece with an edge in three faces or two faces wound against each
    other stay as they are: their side is not theirs to tell.  A closed piece inside another (a cavity, which no
    renderer shows) is turned outward too, as :func:`orient_faces` turns it.

    Parameters
    ----------
    vertices : (V, 3) float
    faces : (F, 3) int

    Returns
    -------
    (F, 3) int64 faces, same order, the turned pieces' reversed
    """
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3).copy()
    if len(f) == 0:
        return f
    v = np.asarray(vertices, dtype=np.float64)
    fa, _, same_dir = _face_pairs(f, len(v))
    label = piece_labels(f)
    tri = v[f]
    area_normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    count = side_counts(f)
    volume = _volumes(v, f, label, _centres(v, f, label)[label])
    keep = _sheets(label, area_normal, volume, count == 1)
    keep[label[fa[same_dir]]] = True
    keep[np.tile(label, 3)[count > 2]] = True
    turn = (~keep & (volume < 0))[label]
    f[turn] = f[turn][:, ::-1]
    return f


def _face_pairs(f: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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


def _flips(fa: np.ndarray, fb: np.ndarray, same_dir: np.ndarray, nf: int) -> tuple[np.ndarray, np.ndarray]:
    """(nf,) bool which faces flip so that every pair agrees with its part's root where a spanning forest of
    the pairs reaches, and (nf,) the part (connected component of the face graph) of each face."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import breadth_first_order, connected_components

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


def face_input(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """``faces`` with each sheet turned where its area faces against the input more than with it: a piece with an
    open edge that encloses almost no volume (``SHEET_VOLUME``: a roof, a terrain, a wall) has no inside for
    :func:`orient_faces`'s signed volume to find, and its side is the input's to tell.  Closed pieces, and open
    ones the signed volume can read (a pose open at the neck), stay as they are.

    Parameters
    ----------
    vertices : (V, 3) float
    faces : (F, 3) int, wound alike within each piece (:func:`orient_faces`)
    points : (P, 3) float, samples of the input surface, in the frame of ``vertices``
    normals : (P, 3) float, their unit normals, pointing out of the input

    Returns
    -------
    (F, 3) int64 faces, same order, the turned pieces' reversed
    """
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3).copy()
    if len(f) == 0 or len(points) == 0:
        return f
    v = np.asarray(vertices, dtype=np.float64)
    tri = v[f]
    area_normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # twice the area along the normal
    label = piece_labels(f)
    n = label.max() + 1
    nearest = cKDTree(np.asarray(points, dtype=np.float64)).query(tri.mean(1))[1]
    vote = np.bincount(label, np.einsum("fd,fd->f", area_normal, np.asarray(normals)[nearest]), n)
    volume = _volumes(v, f, label, _centres(v, f, label)[label])
    return np.where(((vote < 0) & _sheets(label, area_normal, volume, open_sides(f)))[label][:, None], f[:, ::-1], f)


def _sheets(label: np.ndarray, area_normal: np.ndarray, volume: np.ndarray, open_side: np.ndarray) -> np.ndarray:
    """(pieces,) bool: the pieces (faces labelled ``label`` (F,), twice their areas along their normals
    ``area_normal`` (F, 3)) with an open edge (``open_side`` (3F,), per side of ``meshops.face_sides``) whose signed
    volume about their vertices' centroid (``volume`` (pieces,)) is under ``SHEET_VOLUME`` times their area to the
    power 3/2."""
    n = label.max() + 1
    open_piece = np.zeros(n, dtype=bool)
    open_piece[np.tile(label, 3)[open_side]] = True
    area = np.bincount(label, np.linalg.norm(area_normal, axis=1), n) / 2
    return open_piece & (np.abs(volume) < SHEET_VOLUME * area**1.5)


def _centres(v: np.ndarray, f: np.ndarray, label: np.ndarray) -> np.ndarray:
    """(pieces, 3) the mean of each piece's face corners (faces ``f`` (F, 3) labelled ``label`` (F,))."""
    n = label.max() + 1
    centre = np.zeros((n, 3))
    corner = np.repeat(label, 3)
    np.add.at(centre, corner, v[f].reshape(-1, 3))
    return centre / np.maximum(np.bincount(corner, minlength=n), 1)[:, None]


def _volumes(v: np.ndarray, f: np.ndarray, label: np.ndarray, about: np.ndarray) -> np.ndarray:
    """(pieces,) the signed volume of each piece (faces ``f`` (F, 3) labelled ``label`` (F,)) about ``about``: one
    point (3,) for all, or one per face (F, 3); exact for a closed piece wherever the point, an open piece's
    depends on it."""
    t = v[f] - (about if np.ndim(about) == 1 else about[:, None])
    return np.bincount(label, np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])), label.max() + 1) / 6


def sides_asked(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(F,) int8 the side the input asks of each of ``faces`` (F, 3) as wound: 0 where the ``SIDE_SAMPLES`` input
    samples (``points``, ``normals`` (P, 3)) nearest its centroid all face along its normal, 1 where all face
    against it, -1 where they disagree or lie across it (both sides of a part thinner than their spread, a crease).
    Normals that all point into the input (Quake's formats) turn every side: which faces ask alike does not
    change."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(f) == 0 or len(points) == 0:
        return np.full(len(f), -1, dtype=np.int8)
    t = v[f]
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    _, idx = cKDTree(np.asarray(points, dtype=np.float64)).query(t.mean(1), k=min(SIDE_SAMPLES, len(points)))
    dots = np.einsum("fkd,fd->fk", np.asarray(normals, dtype=np.float64)[idx.reshape(len(f), -1)], n)
    return np.where((dots > SIDE_COS).all(1), 0, np.where((dots < -SIDE_COS).all(1), 1, -1)).astype(np.int8)

