"""Quantising a normalised mesh onto the 7-bit grid (``tokenizer.grid``) and the merge it implies.

Vertices sharing a cell become one; the mean continuous position of each merged cell is kept as
the target of the fidelity enhancer, which predicts a residual in [-0.5, 0.5) cells around the
cell centre.
"""

from __future__ import annotations

import numpy as np

from .grid import quantize, sort_key

__all__ = ["clean_faces", "quantize_mesh"]


def quantize_mesh(v: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Quantise a normalised mesh, merge vertices sharing a cell, clean and sort.

    Parameters
    ----------
    v : (N, 3) float
        Normalised positions (unit cube).
    faces : (F, 3) int

    Returns
    -------
    q : (M, 3) int64
        Unique cells in canonical order (``sort_key`` ascending).
    faces : (G, 3) int64
        Faces on ``q``: no repeated index, no duplicate (as a vertex set), each
        rotated so its smallest index comes first (winding kept); sorted.
    cont : (M, 3) float64
        Mean continuous position of the input vertices merged into each cell: the
        target of the fidelity enhancer.
    """
    qv = quantize(v)
    key = sort_key(qv)
    uniq, inverse = np.unique(key, return_inverse=True)
    m = len(uniq)
    q = np.zeros((m, 3), dtype=np.int64)
    q[inverse] = qv
    cont = np.zeros((m, 3))
    np.add.at(cont, inverse, v)
    cont /= np.bincount(inverse, minlength=m)[:, None]
    f = inverse[np.asarray(faces, dtype=np.int64)].reshape(-1, 3)
    f = clean_faces(f)
    used = np.zeros(m, dtype=bool)
    used[f.ravel()] = True
    if not used.all():  # drop vertices only degenerate faces referenced
        remap = np.cumsum(used) - 1
        q, cont, f = q[used], cont[used], remap[f]
    return q, f, cont


def clean_faces(f: np.ndarray) -> np.ndarray:
    """Drop degenerate and duplicate triangles; rotate each to start at its smallest index; sort.

    Two faces on the same three vertices are duplicates whatever their winding.
    """
    f = np.asarray(f, dtype=np.int64).reshape(-1, 3)
    ok = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    f = f[ok]
    if len(f) == 0:
        return f
    r = np.argmin(f, axis=1)
    f = np.stack([f[np.arange(len(f)), (r + k) % 3] for k in range(3)], axis=1)
    _, first = np.unique(np.sort(f, axis=1), axis=0, return_index=True)
    f = f[np.sort(first)]
    return f[np.lexsort((f[:, 2], f[:, 1], f[:, 0]))]
