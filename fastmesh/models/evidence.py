"""Point evidence: a learned logit bias from where the input points lie.

The vertex decoder has to learn that vertices sit on the input surface.  Through
attention alone that takes longer than a CPU budget: after three epochs a decoder
with learned latents and no evidence gains 0.013 nats per token from its condition
(``cond_gain`` in the training log), i.e. it emits the same artist-like sequence for every input.

So the condition also enters the *output*: every candidate token gets a bias read
from counts of input points around the cell it would place a vertex in,

    offset token o in block b:  table[level(n_1), level(n_2), level(n_3)]
    block token b:              block_table[level(n_4)]

where n_s counts the points in the cube of side 2^s cells holding that cell, and
level(n) = min(floor(log2(1 + n)), L - 1) (0 for n < 0 or NaN: ``_level``).  The tables are learned (zeros at start:
no effect until training finds the evidence useful), so the output is a product of
experts: what the transformer expects of an artist mesh, times what the surface
allows.  Counting points is O(P); the bias of a token costs three gathers.

Two more tables read the *sequence* against the surface.  Blocks are emitted in
increasing id order, so from the current block one knows how many blocks holding input
points are still ahead (``remaining``) and how many a candidate block token would jump
over (``skipped``):

    EOS:                        eos_table[level(remaining)]
    block token b (current c):  block_table[level(n_4)] + skip_table[level(skipped(c, b))]

Without them a decoder that has not learned its input well stops early or leaves whole
parts of the shape out (both seen with decoders trained without these tables): ending while occupied
blocks remain, or jumping over them, costs what training finds it costs.  They also keep a decoder
from leaving out the occupied blocks that need no vertex (the flat walls of a box), so with the cell
evidence below they can be left out (``PointEvidence(blocks_ahead=False)``): the sequence is then
read in expected vertices only.

Optionally (``PointEvidence(normals=True)``) a last table reads the input *normals*: artist
vertices sit where the surface bends (corners, creases), rarely inside a flat region, and point
counts alone cannot tell the two apart (a decoder without it filled the flat walls of a building
with hundreds of vertices).  Per cube of side 2^s cells, the spread of the normals in it,

    spread = 1 - |sum of n| / count     (each n with the sign that makes its largest component positive,
                                         so the two sides of a thin sheet count as one direction)

is 0 on a plane and grows with the bend; it is cut into SPREAD_EDGES levels (and one for "no points"),
and an offset token gets  corner_table[state_1, state_2]  from its cubes of side 2 and 4 cells.

With ``PointEvidence(logodds=True)`` the decoder also reads the *cell log-odds* of ``models.cells``
(``CellNet``, a network that scores every cell near the surface for "an artist vertex lies here" from its
local geometry), given as a dense (B, 128^3) grid:

    offset token (cell c):      cell_gain * logodds(c)   (cell_gain starts at 1)
    block token b:              cell_block_table[level(expected vertices in b)]
                                + cell_skip_table[level(expected vertices in the blocks it skips)]
    EOS:                        cell_eos_table[level(expected vertices in the blocks still ahead)]

where a block's expected vertex count is the sum of sigmoid(logodds) over its cells: the decoder
stops when what the cells say is left is covered, and decides which of the likely cells to emit.

Those tables read what lies *ahead* of the current block, never what was emitted, so nothing tells the
decoder it has put 20 vertices in a block that expects one: it ran away on thin shapes (a needle: 421
vertices for 24).  With ``PointEvidence(counts=True)`` three more tables read the sequence's *counts*
against the cells (n: vertices emitted, m: of them in the current block, o: the current offset):

    offset token (stay in the block):  stay_table[level(m), level(expected in the block)]
                                       + rest_table[level(expected in the block after offset o)]
    EOS:                               count_table[given, ratio bucket of n / expected in all]

A face-count target (``target_vertices``) scales every expected amount of the shape by
target / (expected in all), so the same tables that follow the cells follow the target; ``given`` keeps
the EOS reading of a target apart from that of the cells' own estimate, which is looser.
"""

from __future__ import annotations

import torch
from torch import nn

from ..tokenizer import vertex as vt
from ..tokenizer.grid import (
    BLOCK_SIDE,
    BLOCKS_PER_AXIS,
    LEVELS,
    N_OFFSETS,
    OFFSET_BITS,
    block_coords,
    flat_index,
    offset_coords,
    quantize,
)
from .cells import FLOOR, vertex_probabilities

SHIFTS = (1, 2, 3)  # cube sides 2, 4, 8 cells: the 2048 condition points cover a surface sparsely at 1 cell
POINT_LEVELS = 6  # count levels 0, 1, 2-3, 4-7, 8-15, 16+
BLOCK_LEVELS = 8
SEQ_LEVELS = 8  # occupied blocks remaining / skipped: 0, 1, 2-3, ..., 64+
NORMAL_SHIFTS = (1, 2)  # cubes of side 2 and 4 cells for the normal spread
SPREAD_EDGES = (0.01, 0.05, 0.2)  # spread levels: flat, slightly bent, bent, corner (+ "no points")
SPREAD_STATES = len(SPREAD_EDGES) + 2
# Adam moves each parameter by about the learning rate per step: at 1e-3 a zero-initialised table
# would need thousands of steps to reach a bias of a few nats.  Scaling its output lets it get
# there in about a hundred, at the learning rate the transformer needs.
GAIN = 32.0
EXPECTED_LEVELS = 10  # expected vertices: 0, 1, 2-3, ..., 256+
STAY_LEVELS = 8  # vertices emitted in the current block: 0, 1, 2-3, ..., 64+
# log2(emitted / expected) bucket edges of the EOS count reading: a ratio of 1 is the edge at 0.
RATIO_EDGES = (-2.0, -1.0, -0.5, -0.25, -0.1, 0.0, 0.1, 0.25, 0.5, 1.0, 2.0)
RATIO_LEVELS = len(RATIO_EDGES) + 1
_KEY_ORDER: dict = {}  # device -> (128^3,) flat cell index of each (block, offset) key in sequence order
_OFFSET_CELLS: dict = {}  # device -> (4096,) flat cell index of each offset inside block 0


def _key_order(device) -> torch.Tensor:
    """The flat index of cell ``block * N_OFFSETS + offset`` for every key: the grid in the order a
    sequence visits it."""
    if device not in _KEY_ORDER:
        key = torch.arange(N_OFFSETS * BLOCKS_PER_AXIS ** 3, device=device)
        cells = block_coords(key // N_OFFSETS) * BLOCK_SIDE + offset_coords(key % N_OFFSETS)
        _KEY_ORDER[device] = flat_index(cells)
    return _KEY_ORDER[device]


def block_cells(block: torch.Tensor) -> torch.Tensor:
    """(U,) block ids (>= 0) -> (U, 4096) flat indices of their cells, in offset order."""
    if block.device not in _OFFSET_CELLS:
        _OFFSET_CELLS[block.device] = flat_index(offset_coords(torch.arange(N_OFFSETS, device=block.device)))
    return flat_index(block_coords(block) * BLOCK_SIDE)[:, None] + _OFFSET_CELLS[block.device]


def _level(count: torch.Tensor, levels: int) -> torch.Tensor:
    """Count level ``min(floor(log2(1 + count)), levels - 1)``: a row index in ``[0, levels)`` whatever ``count`` holds.

    Parameters
    ----------
    count : (...) int or float tensor
        Amounts that are never negative in exact arithmetic.  A float amount made as a difference of running
        sums can come out a rounding below 0 (CUDA sums in another order than the CPU), and a broken input
        can make it NaN or infinite; indexing a table with the level of such a count is a device-side assert
        on CUDA.  So below 0 counts as 0, NaN as 0 and +inf as the top level.
    levels : int
        Rows of the table the level indexes.

    Returns
    -------
    (...) int64 in ``[0, levels - 1]``; for counts >= 0 exactly the formula above.
    """
    level = torch.log2(1.0 + count.clamp(min=0)).floor()
    return level.nan_to_num(nan=0.0).clamp(0, levels - 1).long()


def _block(block: torch.Tensor) -> torch.Tensor:
    """Current block ids (-1: none yet) held to ``[-1, N_BLOCKS)``, so every lookup made from them stays in its
    table (decoded sequences are always in range; this makes it so by construction)."""
    return block.clamp(-1, vt.N_BLOCKS - 1)


class Evidence:
    """Point counts of one batch of shapes; turns the current block into a logit bias."""

    def __init__(self, module: PointEvidence, points: torch.Tensor, normals: torch.Tensor | None = None,
                 logodds: torch.Tensor | None = None, target_vertices: torch.Tensor | None = None):
        self.tables = module
        b = points.shape[0]
        point_cells = quantize(points.detach().float())  # (B, P, 3)
        self.levels = []  # per shift: (B, res^3) count level of every coarse cube
        for s, n_levels in [(s, POINT_LEVELS) for s in SHIFTS] + [(OFFSET_BITS, BLOCK_LEVELS)]:
            flat = flat_index(point_cells >> s, LEVELS >> s)
            # Counted as integers: exact on every device, so the levels cannot depend on summation order.
            grid = torch.zeros(b, (LEVELS >> s) ** 3, dtype=torch.long, device=points.device)
            grid.scatter_add_(1, flat, torch.ones_like(flat))
            self.levels.append(_level(grid, n_levels))
        # Occupied blocks up to and including each block id (the order blocks are emitted in), as integers.
        occupied = (self.levels[-1] > 0).long()  # (B, 512)
        self.occ_incl = occupied.cumsum(1)
        self.occ_excl = self.occ_incl - occupied
        # The coarse index of cell (block * BLOCK_SIDE + offset) is linear: base(block) + part(offset).
        oxyz = offset_coords(torch.arange(N_OFFSETS, device=points.device))
        self.parts = [flat_index(oxyz >> s, LEVELS >> s) for s in SHIFTS]
        self.spread = None  # per NORMAL_SHIFTS: (B, res^3) spread state of every cube
        if module.corner_table is not None:
            if normals is None:
                raise ValueError("this decoder's evidence reads the input normals: pass them")
            self.spread = [_spread_states(point_cells >> s, normals.detach().float(), LEVELS >> s)
                           for s in NORMAL_SHIFTS]
            self.spread_parts = [flat_index(oxyz >> s, LEVELS >> s) for s in NORMAL_SHIFTS]
        self.logodds = None  # (B, 128^3) cell log-odds
        # (B,) 1 where a face-count target scaled the expected amounts (only a decoder reading its counts reads one)
        self.given = torch.zeros(b, dtype=torch.long, device=points.device)
        if module.cell_gain is not None:
            if logodds is None:
                raise ValueError("this decoder's evidence reads the cell log-odds of models.cells: pass them")
            # A NaN log-odds is no candidate (FLOOR): it would otherwise reach the offsets' logits, and sampling
            # from NaN is an error (on CUDA a device-side assert).
            self.logodds = logodds.float().reshape(b, -1)
            self.logodds = torch.where(self.logodds.isnan(), FLOOR, self.logodds)
            # Expected vertices per block, in block id order (the block of cell (x, y, z) is its top 3 bits).
            per_block = (BLOCKS_PER_AXIS, BLOCK_SIDE) * 3  # (bx, ox, by, oy, bz, oz)
            # Cells at FLOOR are no candidates: they expect nothing (else "nothing ahead" would never be seen before
            # the last blocks).
            p = vertex_probabilities(self.logodds)
            expected = p.reshape(b, *per_block).sum((2, 4, 6)).reshape(b, -1)
            if module.count_table is not None:
                # A target scales what the cells expect to it: (B,) target / expected in all, or 1.
                total = expected.sum(1).clamp(min=1.0)
                given = torch.zeros(b, device=points.device) if target_vertices is None else target_vertices.float()
                self.given = (given > 0).long()
                scale = torch.where(given > 0, given / total, 1.0)
                expected = expected * scale[:, None]
                # Expected vertices up to and including each cell, in sequence order (B, 128^3).
                self.cell_cum = (p[:, _key_order(points.device)] * scale[:, None]).cumsum(1)
                self.ratio_edges = torch.tensor(RATIO_EDGES, device=points.device)  # read at every decode step
            self.cell_expected = expected
            self.cell_incl = expected.cumsum(1)
            self.cell_excl = self.cell_incl - expected

    def logit_bias(self, block: torch.Tensor) -> torch.Tensor:
        """(B, T) current block ids (-1: none yet) -> (B, T, VOCAB) bias (0 on PAD and BOS)."""
        b, t = block.shape
        block = _block(block)
        # A sequence visits a few dozen blocks over hundreds of positions, so the rows of the
        # bias are computed once per distinct (shape, block) and then indexed.
        rows = torch.arange(b, device=block.device)[:, None].expand(b, t)
        key, inverse = torch.unique(rows * (vt.N_BLOCKS + 1) + block + 1, return_inverse=True)
        u_rows, u_block = key // (vt.N_BLOCKS + 1), key % (vt.N_BLOCKS + 1) - 1
        return torch.cat(self._sequence_rows(u_rows, u_block) + [self._offset_rows(u_rows, u_block)],
                         dim=-1)[inverse]

    def count_bias(self, block: torch.Tensor, offset: torch.Tensor, n_vert: torch.Tensor,
                   n_in_block: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The reading of the sequence's counts, per position: :func:`read_counts` of this batch's cells."""
        return read_counts(self.tables, self.cell_expected, self.cell_cum, self.given, self.ratio_edges,
                           _block(block), offset, n_vert, n_in_block)

    def _sequence_rows(self, rows: torch.Tensor, block: torch.Tensor) -> list[torch.Tensor]:
        """(U,) shape index and current block (-1: none) -> [(U, 3) special, (U, 512) block] bias."""
        block_bias = self.tables.block_table(self.levels[-1][rows]).squeeze(-1)
        special = block_bias.new_zeros(len(rows), vt.N_SPECIAL)
        if self.tables.skip_table is not None:  # in occupied blocks
            remaining, skipped = _ahead(self.occ_incl, self.occ_excl, rows, block)
            block_bias = block_bias + self.tables.skip_table(_level(skipped, SEQ_LEVELS)).squeeze(-1)
            special[:, vt.EOS] = self.tables.eos_table(_level(remaining, SEQ_LEVELS)).squeeze(-1)
        if self.logodds is not None:  # the same reading of the sequence, in expected vertices
            ahead, skipped = _ahead(self.cell_incl, self.cell_excl, rows, block)
            block_bias = block_bias + (self.tables.cell_block_table(_level(self.cell_expected[rows], EXPECTED_LEVELS))
                                       + self.tables.cell_skip_table(_level(skipped, EXPECTED_LEVELS))).squeeze(-1)
            special[:, vt.EOS] += self.tables.cell_eos_table(_level(ahead, EXPECTED_LEVELS)).squeeze(-1)
        return [GAIN * special, GAIN * block_bias]

    def _offset_rows(self, rows: torch.Tensor, block: torch.Tensor) -> torch.Tensor:
        """(U,) shape index and block id (-1: none) -> (U, 4096) bias of every offset token."""
        blk = block.clamp(min=0)
        bxyz = block_coords(blk)  # (U, 3)
        idx = None
        for s, lev, part in zip(SHIFTS, self.levels, self.parts, strict=False):
            lv = lev[rows[:, None], flat_index(bxyz * (BLOCK_SIDE >> s), LEVELS >> s)[:, None] + part]  # (U, 4096)
            idx = lv if idx is None else idx * POINT_LEVELS + lv
        bias = self.tables.table(idx).squeeze(-1)
        if self.spread is not None:
            idx = None
            for s, st, part in zip(NORMAL_SHIFTS, self.spread, self.spread_parts, strict=True):
                sv = st[rows[:, None], flat_index(bxyz * (BLOCK_SIDE >> s), LEVELS >> s)[:, None] + part]
                idx = sv if idx is None else idx * SPREAD_STATES + sv
            bias = bias + self.tables.corner_table(idx).squeeze(-1)
        bias = GAIN * bias
        if self.logodds is not None:
            bias = bias + self._cell_rows(rows, blk)
        return bias * (block >= 0)[:, None]  # no block yet: no evidence

    def _cell_rows(self, rows: torch.Tensor, block: torch.Tensor) -> torch.Tensor:
        """(U,) shape index and block id (>= 0) -> (U, 4096) cell term of every offset token's bias."""
        return self.tables.cell_gain * self.logodds[rows[:, None], block_cells(block)]

    @property
    def reads_logodds(self) -> bool:
        return self.logodds is not None

    def offset_cells(self, block: torch.Tensor) -> torch.Tensor:
        """(B,) current blocks -> (B, 4096) the cell term of the offsets' bias (0 before the first block)."""
        rows = torch.arange(len(block), device=block.device)
        block = _block(block)
        return self._cell_rows(rows, block.clamp(min=0)) * (block >= 0)[:, None]

    def _unless_target(self, own: float, asked: float) -> torch.Tensor:
        """(B,) ``own`` where the cells' own estimate sets the count, ``asked`` where a face-count target does."""
        return torch.where(self.given > 0, asked, own)

    def weighted_cells(self, block: torch.Tensor, weight: float) -> torch.Tensor:
        """(B,) current blocks -> (B, 4096) what a cell weight adds to the offsets' bias: (weight - 1) x their cell
        term where the cells' own estimate sets the count, nothing where a face-count target does (the weight
        favours a block's likeliest cells, jumping over those before them in sequence order, so blocks end early:
        targets of 1,000 faces and more were undershot)."""
        return self.offset_cells(block) * self._unless_target(weight - 1.0, 0.0)[:, None]

    def expected_through(self, block: torch.Tensor, pace: float = 1.0) -> torch.Tensor:
        """(B,) current blocks -> (B,) the cells' expected vertices in the blocks up to and including them, x
        ``pace`` where they are the cells' own estimate: scaled to a face-count target they are the count asked
        for, which ``pace`` leaves as it is."""
        rows = torch.arange(len(block), device=block.device)
        block = _block(block)
        return self.cell_incl[rows, block.clamp(min=0)] * (block >= 0) * self._unless_target(pace, 1.0)


def read_counts(tables: PointEvidence, expected: torch.Tensor, cum: torch.Tensor, given: torch.Tensor,
                ratio_edges: torch.Tensor, block: torch.Tensor, offset: torch.Tensor, n_vert: torch.Tensor,
                n_in_block: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The count tables' reading of B sequences against their shapes' cells.

    ``expected`` (B, N_BLOCKS) expected vertices per block, ``cum`` (B, 128^3) expected vertices up to each
    cell in sequence order, ``given`` (B,) 1 where a target scaled them (all as ``Evidence`` keeps them);
    (B, T) current block and offset (-1: none), vertices emitted and of them in the current block ->
    (B, T) bias of EOS and (B, T) bias of every offset token (both 0 before the first block).  Gathers and
    table lookups only, so a row reads the same alone or stacked with others.
    """
    rows = torch.arange(block.shape[0], device=block.device)[:, None].expand_as(block)
    block = _block(block)
    blk = block.clamp(min=0)
    in_block = expected[rows, blk]
    # Expected in the block after offset o: the running sum at the block's last cell less that at o.
    end = cum[rows, blk * N_OFFSETS + N_OFFSETS - 1]
    key = blk * N_OFFSETS + offset.clamp(-1, N_OFFSETS - 1)
    rest = (end - torch.where(key >= 0, cum[rows, key.clamp(min=0)], 0.0)).clamp(min=0)
    stay = (tables.stay_table(_level(n_in_block, STAY_LEVELS) * EXPECTED_LEVELS + _level(in_block, EXPECTED_LEVELS))
            + tables.rest_table(_level(rest, EXPECTED_LEVELS))).squeeze(-1)
    total = cum[:, -1].clamp(min=1.0)[:, None]
    ratio = torch.bucketize(torch.log2(n_vert.float().clamp(min=0.5) / total), ratio_edges)
    eos = tables.count_table(given[:, None] * RATIO_LEVELS + ratio).squeeze(-1)
    on = (block >= 0).float()
    return GAIN * eos * on, GAIN * stay * on


def _ahead(incl: torch.Tensor, excl: torch.Tensor, rows: torch.Tensor, block: torch.Tensor
           ) -> tuple[torch.Tensor, torch.Tensor]:
    """What lies ahead of the current block, from per-block amounts summed in block order.

    ``incl`` / ``excl`` (B, N_BLOCKS): running sums with / without each block; ``rows`` (U,) shape index,
    ``block`` (U,) current block (-1: none yet).  Returns (U,) the amount after the current block and
    (U, N_BLOCKS) the amount a jump to each block would pass over (strictly between), both >= 0 (float running
    sums read at two places can differ by a rounding the wrong way).
    """
    done = incl[rows, block.clamp(min=0)] * (block >= 0)  # emitted so far
    return (incl[rows, -1] - done).clamp(min=0), (excl[rows] - done[:, None]).clamp(min=0)


def _spread_states(coarse: torch.Tensor, normals: torch.Tensor, res: int) -> torch.Tensor:
    """(B, P, 3) coarse cells and (B, P, 3) unit normals -> (B, res^3) spread state (0: no points)."""
    b = coarse.shape[0]
    flat = flat_index(coarse, res)  # (B, P)
    # One sign per direction: the largest component positive (n and -n then agree).
    big = normals.abs().argmax(-1, keepdim=True)
    n = normals * torch.where(normals.gather(-1, big) < 0, -1.0, 1.0)
    total = torch.zeros(b, res ** 3, 3, device=normals.device)
    total.scatter_add_(1, flat[..., None].expand(-1, -1, 3), n)
    count = torch.zeros(b, res ** 3, device=normals.device)
    count.scatter_add_(1, flat, torch.ones_like(flat, dtype=count.dtype))
    spread = 1.0 - total.norm(dim=-1) / count.clamp(min=1)
    edges = torch.tensor(SPREAD_EDGES, device=normals.device)
    return torch.where(count > 0, 1 + torch.bucketize(spread, edges), 0)


class PointEvidence(nn.Module):
    """The learned tables of :class:`Evidence` (POINT_LEVELS^3 + BLOCK_LEVELS scalars, 2 * SEQ_LEVELS with
    ``blocks_ahead``, SPREAD_STATES^2 with ``normals``, 1 + 3 * EXPECTED_LEVELS with ``logodds``,
    (STAY_LEVELS + 1) * EXPECTED_LEVELS + 2 * RATIO_LEVELS with ``counts``)."""

    def __init__(self, normals: bool = False, logodds: bool = False, blocks_ahead: bool = True,
                 counts: bool = False):
        super().__init__()
        if not (blocks_ahead or logodds):
            raise ValueError("the sequence needs one reading of what is ahead: occupied blocks or the cells")
        if counts and not logodds:
            raise ValueError("the count reading compares the sequence with the cells: it needs logodds=True")
        self.table = nn.Embedding(POINT_LEVELS ** len(SHIFTS), 1)
        self.block_table = nn.Embedding(BLOCK_LEVELS, 1)
        self.skip_table = nn.Embedding(SEQ_LEVELS, 1) if blocks_ahead else None
        self.eos_table = nn.Embedding(SEQ_LEVELS, 1) if blocks_ahead else None
        self.corner_table = nn.Embedding(SPREAD_STATES ** len(NORMAL_SHIFTS), 1) if normals else None
        # The cell log-odds are calibrated: added at full weight from the start (a product of experts).  Not
        # scaled by GAIN like the tables: its gradient (a mean of log-odds, several nats) would then dominate
        # the clipped gradient norm (56 against ~3) and stall the transformer.
        self.cell_gain = nn.Parameter(torch.ones(())) if logodds else None
        self.cell_block_table = nn.Embedding(EXPECTED_LEVELS, 1) if logodds else None
        self.cell_skip_table = nn.Embedding(EXPECTED_LEVELS, 1) if logodds else None
        self.cell_eos_table = nn.Embedding(EXPECTED_LEVELS, 1) if logodds else None
        self.stay_table = nn.Embedding(STAY_LEVELS * EXPECTED_LEVELS, 1) if counts else None
        self.rest_table = nn.Embedding(EXPECTED_LEVELS, 1) if counts else None
        self.count_table = nn.Embedding(2 * RATIO_LEVELS, 1) if counts else None
        for t in (self.table, self.block_table, self.skip_table, self.eos_table, self.corner_table,
                  self.cell_block_table, self.cell_skip_table, self.cell_eos_table, self.stay_table,
                  self.rest_table, self.count_table):
            if t is not None:
                nn.init.zeros_(t.weight)

    def forward(self, points: torch.Tensor, normals: torch.Tensor | None = None,
                logodds: torch.Tensor | None = None, target_vertices: torch.Tensor | None = None) -> Evidence:
        """(B, P, 3) points in the unit cube (and their normals, (B, 128^3) cell log-odds and (B,) vertex
        counts asked for, 0: none) -> their :class:`Evidence`."""
        return Evidence(self, points, normals, logodds, target_vertices)
