"""The cells a vertex sequence may take: those the cell evidence scores at least ``SamplingConfig.cell_floor``.

The cell network spreads a thin probability over every flat region (what the corpus's artists do
there on average): on 48 meshes of the held-out packages 37 % of its expected vertices lie in cells
below log-odds -4, while 86 % of the artists' vertices have a cell at -4 or above within one cell.  On a shape
whose artist left the walls bare, the decoder spent its count there: a Warzone building of 26 vertices
came back with 135, most of them on its walls.  Below the floor a cell takes no vertex, and a block
with no cell at the floor is not entered (the grammar needs an offset after a block token).

Rows with a face-count target are left open (the count is the one asked for), and so is a row whose
floor leaves no block at all.

Off by default (``SamplingConfig``): the same thin spread lies along smooth curved surfaces, where
artists do put vertices; a floor of -4 raised vertex precision on the held-out packages and lost
those vertices (a wheel's cylinder), and with them CD and HD (docs/results.md).
"""

from __future__ import annotations

import torch

from ..tokenizer import vertex as vt
from ..tokenizer.grid import BLOCK_SIDE, BLOCKS_PER_AXIS, N_BLOCKS
from .evidence import block_cells


class CellGate:
    """The open blocks and offsets of B shapes.

    Parameters
    ----------
    cells : (B, 128^3) cell log-odds of each row's shape.
    free : (B,) bool, rows left wholly open (a face-count target).
    floor : log-odds below which a cell is closed.
    """

    def __init__(self, cells: torch.Tensor, free: torch.Tensor, floor: float):
        b = cells.shape[0]
        self.cells, self.floor = cells, floor
        per_block = (b,) + (BLOCKS_PER_AXIS, BLOCK_SIDE) * 3
        self.open_blocks = cells.reshape(per_block).amax((2, 4, 6)).reshape(b, N_BLOCKS) >= floor
        self.free = free.bool() | ~self.open_blocks.any(1)
        self.open_blocks |= self.free[:, None]

    def offsets(self, block: torch.Tensor) -> torch.Tensor:
        """(B,) current blocks -> (B, 4096) open offsets (all of them before the first block)."""
        rows = torch.arange(len(block), device=block.device)
        scores = self.cells[rows[:, None], block_cells(block.clamp(min=0))]
        return (scores >= self.floor) | (self.free | (block < 0))[:, None]

    def mask(self, mask: torch.Tensor, blocks: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
        """(L, VOCAB) grammar mask with the closed block and offset tokens masked out: (L, 512) open blocks and
        (L, 4096) open offsets of the same rows (``open_blocks`` / ``offsets`` indexed)."""
        mask[:, vt.BLOCK0:vt.OFFSET0] &= blocks
        mask[:, vt.OFFSET0:] &= offsets
        return mask
