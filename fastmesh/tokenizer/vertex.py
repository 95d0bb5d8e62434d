"""FastMesh's block-wise vertex tokenizer (7-bit, 8 blocks x 16 offsets per axis).

A cell q = 16 * block + offset per axis.  Vertices are sorted by (block id, offset id);
a block token is emitted only when the block changes, then one offset token per vertex:

    BOS  B(b0) O(o0) O(o1) ...  B(b1) O(o) ...  EOS

Vocabulary (4611 ids, as the authors'): 0 PAD, 1 BOS, 2 EOS, 3..514 blocks, 515..4610 offsets.

Valid sequences form a grammar whose allowed next tokens are always contiguous id
ranges, so constrained decoding is a cheap range mask (``allowed_ranges``).
"""

from __future__ import annotations

import numpy as np

from .grid import N_BLOCKS, N_OFFSETS, cells_from_keys, check_cells, sort_key, split_key

PAD, BOS, EOS = 0, 1, 2
N_SPECIAL = 3
BLOCK0 = N_SPECIAL
OFFSET0 = N_SPECIAL + N_BLOCKS
VOCAB_SIZE = N_SPECIAL + N_BLOCKS + N_OFFSETS  # 4611


def encode(q: np.ndarray) -> np.ndarray:
    """(N, 3) int cells in [0, 127] -> int64 token ids, BOS ... EOS.

    Cells are sorted and de-duplicated first, so any order of the same set gives
    the same tokens.
    """
    q = np.asarray(q, dtype=np.int64).reshape(-1, 3)
    check_cells(q)
    key = np.unique(sort_key(q))
    block, offset = split_key(key)
    new_block = np.ones(len(key), dtype=bool)
    new_block[1:] = block[1:] != block[:-1]
    n_tok = len(key) + int(new_block.sum())
    out = np.empty(n_tok + 2, dtype=np.int64)
    out[0], out[-1] = BOS, EOS
    # Position of each offset token: its index plus the number of block tokens up to it.
    pos_off = np.arange(len(key)) + np.cumsum(new_block) + 1
    out[pos_off] = OFFSET0 + offset
    out[pos_off[new_block] - 1] = BLOCK0 + block[new_block]
    return out


def decode(tokens: np.ndarray, strict: bool = True) -> np.ndarray:
    """Token ids -> (N, 3) int64 cells in canonical order.

    BOS/PAD are skipped, decoding stops at EOS.  With ``strict`` a grammar violation
    (offset before any block, non-increasing order) raises ValueError; otherwise the
    offending tokens are dropped.
    """
    toks = np.asarray(tokens, dtype=np.int64).ravel()
    cells, block, last = [], -1, -1
    for t in toks:
        t = int(t)
        if t == EOS:
            break
        if t < N_SPECIAL:
            continue
        if t < OFFSET0:
            b = t - BLOCK0
            if b <= block:
                if strict:
                    raise ValueError(f"block {b} does not increase after {block}")
                continue
            block = b
            continue
        if block < 0:
            if strict:
                raise ValueError("offset token before any block token")
            continue
        key = block * N_OFFSETS + (t - OFFSET0)
        if key <= last:
            if strict:
                raise ValueError("offsets must strictly increase within a block")
            continue
        last = key
        cells.append(key)
    return cells_from_keys(np.array(cells, dtype=np.int64))


def num_tokens(q: np.ndarray) -> int:
    """Length of ``encode(q)`` without building it (BOS and EOS included)."""
    key = np.unique(sort_key(np.asarray(q).reshape(-1, 3)))
    return len(key) + len(np.unique(split_key(key)[0])) + 2


def allowed_ranges(prev: int, block: int, offset: int) -> list[tuple[int, int]]:
    """Half-open token-id ranges allowed after ``prev``.

    Parameters
    ----------
    prev : int
        The last token.
    block : int
        Current block id (-1 before the first block token).
    offset : int
        Last offset id emitted in the current block (-1 right after a block token).
    """
    if prev == BOS:
        return [(BLOCK0, BLOCK0 + N_BLOCKS)]
    if BLOCK0 <= prev < OFFSET0:
        return [(OFFSET0, VOCAB_SIZE)]
    if prev >= OFFSET0:
        return [(EOS, EOS + 1), (BLOCK0 + block + 1, OFFSET0), (OFFSET0 + offset + 1, VOCAB_SIZE)]
    return [(PAD, PAD + 1)]  # after EOS/PAD: padding only
