"""The 7-bit cell grid: its constants, cell centres, and the block/offset bit layout of a cell.

The unit cube [-0.5, 0.5]^3 is cut into ``LEVELS`` = 128 cells per axis.  A position v maps to
the cell q = clip(floor((v + 0.5) * 128), 0, 127) per axis, and a cell back to its *centre*
(q + 0.5) / 128 - 0.5, so the round trip moves a point by at most half a cell per axis.

Each cell coordinate splits into a block (its top ``BLOCK_BITS`` = 3 bits) and an offset inside
the block (its low ``OFFSET_BITS`` = 4 bits): q = BLOCK_SIDE * block + offset with BLOCK_SIDE = 16.
The vertex tokenizer names a cell by its block id (the three block coordinates, x major, 0..511)
and its offset id (the three offsets, x major, 0..4095); ``sort_key`` = block id * 4096 + offset id
orders cells as the tokenizer emits them.

Every function takes numpy arrays (or anything ``np.asarray`` reads) and torch tensors alike and
answers in the same kind: the same arithmetic serves the tokenizer (numpy) and the models (torch,
on any device).  Integer results are int64; cell centres are float64 from numpy and the default
float dtype (float32) from integer tensors.
"""

from __future__ import annotations

import numpy as np

BITS = 7
LEVELS = 1 << BITS  # 128 cells per axis
N_CELLS = LEVELS ** 3
CELL = 1.0 / LEVELS  # the side of one cell in the unit cube
OFFSET_BITS = 4
BLOCK_BITS = BITS - OFFSET_BITS
BLOCK_SIDE = 1 << OFFSET_BITS  # 16 cells per block per axis
BLOCKS_PER_AXIS = 1 << BLOCK_BITS  # 8
N_BLOCKS = BLOCKS_PER_AXIS ** 3  # 512 block ids
N_OFFSETS = BLOCK_SIDE ** 3  # 4096 offset ids


def _is_tensor(x) -> bool:
    # Duck-typed so that the tokenizer (numpy only) never imports torch.
    return type(x).__module__.startswith("torch")


def _int64(x):
    return x.long() if _is_tensor(x) else np.asarray(x, dtype=np.int64)


def _stack(parts: list):
    """Stack along a new last axis, in the kind of ``parts[0]``."""
    if _is_tensor(parts[0]):
        import torch

        return torch.stack(parts, dim=-1)
    return np.stack(parts, axis=-1)


def grid_coords(v):
    """Positions in the unit cube -> continuous grid coordinates (cell c spans [c, c + 1) per axis).

    Parameters
    ----------
    v : (…, 3) float array or tensor
        Tensors keep their dtype (pass ``.double()`` where the floor must be exact in float64).

    Returns
    -------
    (…, 3) float64 array, or a tensor of ``v``'s dtype.
    """
    v = v if _is_tensor(v) else np.asarray(v, dtype=np.float64)
    return (v + 0.5) * LEVELS


def quantize(v):
    """(…, 3) float positions in the unit cube -> (…, 3) int64 cells in [0, 127] (see ``grid_coords``).

    Always on the grid, so a cell indexes any table of the grid: positions beyond the cube go to its border
    cell (infinities included) and NaN to cell 0 (cast to an integer, NaN would be an arbitrary index).
    """
    g = grid_coords(v).clip(0, LEVELS - 1) // 1  # clipping first keeps +-inf out of the floor division
    return _int64(g.nan_to_num(0.0) if _is_tensor(g) else np.nan_to_num(g, nan=0.0))


def dequantize(q):
    """(…, 3) int cells -> (…, 3) cell centres in (-0.5, 0.5): float64 arrays, or float tensors."""
    q = q if _is_tensor(q) else np.asarray(q, dtype=np.float64)
    return (q + 0.5) / LEVELS - 0.5


def check_cells(q: np.ndarray) -> None:
    """Raise ValueError unless every coordinate of ``q`` (an int array) lies on the grid."""
    if len(q) and (q.min() < 0 or q.max() >= LEVELS):
        raise ValueError(f"vertex cells must lie in [0, {LEVELS - 1}]")


def flat_index(c, res: int = LEVELS):
    """(…, 3) int coordinates -> (…) int64 flat index in a res^3 grid, x major (the 128^3 grid by default)."""
    c = _int64(c)
    return (c[..., 0] * res + c[..., 1]) * res + c[..., 2]


def unflat_index(flat, res: int = LEVELS):
    """(…) flat index in a res^3 grid -> (…, 3) int64 coordinates: the inverse of ``flat_index``."""
    flat = _int64(flat)
    return _stack([flat // (res * res), (flat // res) % res, flat % res])


def split_cells(q) -> tuple:
    """(…, 3) int cells -> their (…) int64 block ids and (…) int64 offset ids (the tokenizer's layout)."""
    q = _int64(q)
    return flat_index(q >> OFFSET_BITS, BLOCKS_PER_AXIS), flat_index(q & (BLOCK_SIDE - 1), BLOCK_SIDE)


def block_coords(block):
    """(…) block ids -> (…, 3) int64 block coordinates in [0, 8)."""
    return unflat_index(block, BLOCKS_PER_AXIS)


def offset_coords(offset):
    """(…) offset ids -> (…, 3) int64 offsets inside a block, in [0, 16)."""
    return unflat_index(offset, BLOCK_SIDE)


def join_cells(block, offset):
    """(…) block ids and (…) offset ids -> (…, 3) int64 cells: the inverse of ``split_cells``."""
    return block_coords(block) * BLOCK_SIDE + offset_coords(offset)


def sort_key(q):
    """Canonical vertex order: (…, 3) int cells -> (…) int64 block id * 4096 + offset id.

    The key reorders the bits of (x, y, z) as (x_hi, y_hi, z_hi, x_lo, y_lo, z_lo).
    """
    block, offset = split_cells(q)
    return block * N_OFFSETS + offset


def split_key(key) -> tuple:
    """(…) ``sort_key`` values -> their (…) int64 block ids and (…) int64 offset ids."""
    key = _int64(key)
    return key // N_OFFSETS, key % N_OFFSETS


def cells_from_keys(key):
    """(…) ``sort_key`` values -> (…, 3) int64 cells: the inverse of ``sort_key``."""
    return join_cells(*split_key(key))
