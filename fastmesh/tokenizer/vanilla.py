"""Vanilla whole-mesh tokenizer: 9 coordinate tokens per face (the PolyGen / MeshGPT baseline).

The mesh is first put in canonical form (:func:`canonical_mesh`): unique cells sorted by
``sort_key``, faces rotated to start at their smallest index (winding kept), duplicates and
degenerate faces dropped, faces sorted.  Each face then emits its three vertices' x, y, z
cells in winding order:

    BOS  x0 y0 z0 x1 y1 z1 x2 y2 z2  ...  EOS

Vocabulary (131 ids): 0 PAD, 1 BOS, 2 EOS, 3 + c for a cell coordinate c in [0, 127].

Decoding rebuilds the mesh from the triangle soup by merging equal cells, so it returns the
canonical form of the encoded mesh exactly (same vertex order, same faces, same winding).
Vertices no face references are not representable and are lost.
"""

from __future__ import annotations

import numpy as np

from .grid import LEVELS, cells_from_keys, check_cells, sort_key
from .quantize import clean_faces

PAD, BOS, EOS = 0, 1, 2
N_SPECIAL = 3
COORD0 = N_SPECIAL
VOCAB_SIZE = N_SPECIAL + LEVELS  # 131
TOKENS_PER_FACE = 9


def canonical_mesh(q: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Canonical form of a quantised mesh, the form every whole-mesh tokenizer round-trips.

    Parameters
    ----------
    q : (V, 3) int
        Cells in [0, 127], any order, repeats allowed (equal cells are merged).
    faces : (F, 3) int
        Triangles indexing ``q``.

    Returns
    -------
    q : (M, 3) int64
        Referenced unique cells, ascending ``sort_key``.
    faces : (G, 3) int64
        Cleaned faces (see ``quantize.clean_faces``), each starting at its smallest index.
    """
    q = np.asarray(q, dtype=np.int64).reshape(-1, 3)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    check_cells(q)
    if faces.size and (faces.min() < 0 or faces.max() >= len(q)):
        raise ValueError("face indices out of range")
    keys, inverse = np.unique(sort_key(q), return_inverse=True)
    f = clean_faces(inverse.reshape(-1)[faces])
    used = np.zeros(len(keys), dtype=bool)
    used[f.ravel()] = True
    remap = np.cumsum(used) - 1
    return cells_from_keys(keys[used]), remap[f].reshape(-1, 3)


def mesh_from_soup(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(3F, 3) cells, three corners per face in winding order -> canonical (q, faces)."""
    corners = np.asarray(corners, dtype=np.int64).reshape(-1, 3)
    keys, inverse = np.unique(sort_key(corners), return_inverse=True)
    return canonical_mesh(cells_from_keys(keys), inverse.reshape(-1, 3))


def encode(q: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Quantised mesh -> int64 tokens ``BOS, 9 per face, EOS``."""
    q, f = canonical_mesh(q, faces)
    out = np.empty(TOKENS_PER_FACE * len(f) + 2, dtype=np.int64)
    out[0], out[-1] = BOS, EOS
    out[1:-1] = COORD0 + q[f].reshape(-1)
    return out


def decode(tokens: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tokens -> canonical (q, faces).

    BOS and PAD are skipped and decoding stops at EOS.  A trailing incomplete face is
    dropped (a truncated generation still yields its complete faces).
    """
    t = np.asarray(tokens, dtype=np.int64).ravel()
    stop = np.flatnonzero(t == EOS)
    if len(stop):
        t = t[: stop[0]]
    t = t[t >= COORD0]
    if len(t) and t.max() >= VOCAB_SIZE:
        raise ValueError(f"token id {int(t.max())} outside the vanilla vocabulary ({VOCAB_SIZE})")
    n = len(t) // TOKENS_PER_FACE * TOKENS_PER_FACE
    return mesh_from_soup(t[:n] - COORD0)


def num_tokens(q: np.ndarray, faces: np.ndarray) -> int:
    """Length of ``encode(q, faces)`` (BOS and EOS included)."""
    return TOKENS_PER_FACE * len(canonical_mesh(q, faces)[1]) + 2
