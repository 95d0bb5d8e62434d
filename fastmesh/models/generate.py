"""Sampling vertex sequences from a :class:`VertexDecoder`.

Grammar-constrained: every step masks the logits to the tokens the vertex grammar
allows (block then offsets, strictly increasing, EOS only after a vertex), so
every sequence decodes to distinct, valid vertices.  ``max_vertices`` forces EOS
once the budget is spent.  Temperature 0 is greedy decoding.

Each token is chosen in two steps (``choose_next``): its kind (EOS, a new block, another
vertex in this block) from the decoder's own probabilities at ``structure_temperature``,
then the token of that kind at ``temperature``, the offsets with the cell evidence weighted
by ``cell_weight``.  With cell evidence, ``pace_mask`` also closes the current block once the
sequence runs ahead of ``pace`` x the cells' expected vertices.  These settings trade count for precision, so
neither applies where a face-count target sets the count (``Evidence.weighted_cells``,
``Evidence.expected_through``).

The loop is gpt-fast's: a :class:`DecodeState` of every row's grammar state, and per step the evidence's bias
(``biased_logits``, read again only when a row enters a new block: :class:`BlockReading`), the tokens the grammar
and the pace allow (``allowed``), the draw (``choose_next``), the state moved past it (``DecodeState.advance``)
and the next token through the decoder.

A batch of sequences is decoded in lockstep, one decode step for all of them (the step
is bound by reading the weights, so B sequences cost little more than one).  Each row
keeps its own grammar state, evidence and random generator (row k draws from seed
``cfg.seed + k``), so row k is the sequence that prefix row k gives decoded alone with
that seed; a finished row leaves the batch.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from ..params import BOUNDS, SamplingConfig
from ..tokenizer import vertex as vt
from .choice import choose_next, pace_mask
from .evidence import Evidence, read_counts
from .kv_cache import KVCache
from .vertex import VertexDecoder, add_count_bias, grammar_mask, grammar_mask_rows, grammar_state


class Cancelled(Exception):
    """Raised when a ``should_cancel`` callback asks generation to stop."""


class GenerationError(RuntimeError):
    """The networks ran but produced no usable mesh (``code`` says why)."""

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code, self.message = code, message


class StackedEvidence:
    """The evidence of B shapes, each computed alone, read as one batch.

    Row i's bias is exactly what its own evidence gives, however that evidence computes it
    (a batched computation may round differently from a single one).
    """

    def __init__(self, rows: list[Evidence]):
        self.rows = rows
        self._counts = None  # the rows' count inputs stacked, made on the first count reading
        self._last: dict[tuple, list] = {}  # per reading: each row's last (block, result)

    def _per_row(self, name: str, block: torch.Tensor, *args) -> torch.Tensor:
        """``rows[i].<name>(block[i:i + 1], *args)`` stacked over the rows.  The decode loop reads again when
        any row enters a new block; a row still in the block it last read gives that reading again."""
        last = self._last.setdefault((name, *args), [None] * len(self.rows))
        for i, e in enumerate(self.rows):
            key = block[i].tolist()
            if last[i] is None or last[i][0] != key:
                last[i] = (key, getattr(e, name)(block[i:i + 1], *args))
        return torch.cat([x[1] for x in last])

    def logit_bias(self, block: torch.Tensor) -> torch.Tensor:
        """(B, T) current block ids -> (B, T, VOCAB) bias, row i from ``rows[i]``."""
        return self._per_row("logit_bias", block)

    def count_bias(self, block: torch.Tensor, offset: torch.Tensor, n_vert: torch.Tensor,
                   n_in_block: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, T) sequence state -> (B, T) EOS and (B, T) offset bias, row i from ``rows[i]``.

        One reading over the rows stacked (it is read at every step): gathers and lookups, the same per row.
        """
        if self._counts is None:
            self._counts = [torch.cat([getattr(e, name) for e in self.rows])
                            for name in ("cell_expected", "cell_cum", "given")]
        first = self.rows[0]
        return read_counts(first.tables, *self._counts, first.ratio_edges, block, offset, n_vert, n_in_block)

    @property
    def reads_logodds(self) -> bool:
        return self.rows[0].reads_logodds

    def weighted_cells(self, block: torch.Tensor, weight: float) -> torch.Tensor:
        """(B,) current blocks -> (B, N_OFFSETS) ``Evidence.weighted_cells`` of each row."""
        return self._per_row("weighted_cells", block, weight)

    def expected_through(self, block: torch.Tensor, pace: float = 1.0) -> torch.Tensor:
        """(B,) current blocks -> (B,) ``Evidence.expected_through`` of each row."""
        return self._per_row("expected_through", block, pace)


def new_cache(model: VertexDecoder, batch: int, length: int, device, dtype) -> KVCache:
    """An empty cache of ``length`` positions for ``batch`` rows (another backend, ``onnx_decode.OrtDecoder``,
    brings its own layout)."""
    if hasattr(model, "new_cache"):  # models.onnx_decode
        return model.new_cache(batch, length, device, dtype)
    c = model.cfg
    return KVCache(c.depth, batch, c.heads, length, c.head_dim, device=device, dtype=dtype)


@dataclass
class DecodeState:
    """The grammar state of B rows, each (B,) int64, and the tokens so far."""

    block: torch.Tensor  # current block, -1 before the first
    offset: torch.Tensor  # last offset in the current block, -1 right after a block token
    prev: torch.Tensor  # last token
    n_vert: torch.Tensor  # vertices so far
    n_in_block: torch.Tensor  # vertices so far in the current block
    live: torch.Tensor  # (L,) the rows still decoding, in order: the rows of the logits and of the cache
    out: list[torch.Tensor]  # each step's (B,) tokens, PAD in the rows that have left

    @classmethod
    def start(cls, batch: int, device) -> DecodeState:
        """Every row at BOS."""
        def full(v):
            return torch.full((batch,), v, dtype=torch.long, device=device)

        bos = full(vt.BOS)
        return cls(full(-1), full(-1), bos, full(0), full(0), torch.arange(batch, device=device), [bos])

    def advance(self, picked: torch.Tensor) -> torch.Tensor:
        """Move the live rows past their (L,) ``picked`` tokens; returns the (B,) step's tokens."""
        nxt = torch.full_like(self.prev, vt.PAD)
        nxt[self.live] = picked
        self.out.append(nxt)
        is_block = (nxt >= vt.BLOCK0) & (nxt < vt.OFFSET0)
        is_off = nxt >= vt.OFFSET0
        self.block = torch.where(is_block, nxt - vt.BLOCK0, self.block)
        self.offset = torch.where(is_off, nxt - vt.OFFSET0, torch.where(is_block, -1, self.offset))
        self.n_vert = self.n_vert + is_off.long()
        self.n_in_block = torch.where(is_block, 0, self.n_in_block + is_off.long())
        self.prev = nxt
        return nxt

    def keep(self, going: torch.Tensor, cache: KVCache) -> None:
        """Only the live rows flagged in ``going`` (L,) stay in the batch and its cache."""
        rows = going.nonzero()[:, 0]
        cache.select(rows)
        self.live = self.live[rows]


@dataclass
class BlockReading:
    """What the evidence says of the rows' current blocks (each (B, ...)); it changes only when a row enters a new
    block, so it is read again only then."""

    block: torch.Tensor | None = None  # the blocks it was read for
    bias: torch.Tensor | None = None  # (B, VOCAB) logit bias
    cell_bias: torch.Tensor | None = None  # (B, 4096) cell weight on the offsets (decoders that read the cells)
    through: torch.Tensor | None = None  # (B,) the cells' expected vertices up to the block's end, times the pace

    def update(self, evidence: Evidence | StackedEvidence, block: torch.Tensor, cfg: SamplingConfig) -> None:
        if self.block is not None and torch.equal(block, self.block):
            return
        self.bias, self.block = evidence.logit_bias(block[:, None])[:, 0], block.clone()
        if evidence.reads_logodds:
            self.cell_bias = evidence.weighted_cells(block, cfg.cell_weight)
            self.through = evidence.expected_through(block, cfg.pace)


def biased_logits(logits: torch.Tensor, s: DecodeState, evidence: Evidence | StackedEvidence | None,
                  reading: BlockReading, cfg: SamplingConfig, counts: bool) -> torch.Tensor:
    """(L, VOCAB) decoder logits of the live rows plus the evidence's bias and, with ``counts``, its count bias."""
    if evidence is None:
        return logits
    reading.update(evidence, s.block, cfg)
    logits = logits + reading.bias[s.live]
    if counts:  # read with every vertex
        eos, stay = evidence.count_bias(s.block[:, None], s.offset[:, None], s.n_vert[:, None], s.n_in_block[:, None])
        logits = add_count_bias(logits, eos[s.live, 0], stay[s.live, 0])
    return logits


def allowed(s: DecodeState, cfg: SamplingConfig, reading: BlockReading) -> torch.Tensor:
    """(L, VOCAB) bool: the tokens the grammar allows the live rows, and the pace where the cells are read."""
    live = s.live
    mask = grammar_mask_rows(s.prev[live].tolist(), s.block[live].tolist(), s.offset[live].tolist(),
                             (s.n_vert[live] >= cfg.max_vertices).tolist(), s.prev.device)
    if reading.through is not None and cfg.pace > 0:
        mask[:, vt.OFFSET0:] &= ~pace_mask(reading.through, s.prev, s.n_vert)[live, None]
    return mask


def sequences(tokens: torch.Tensor) -> list[torch.Tensor]:
    """(B, T) tokens -> each row up to its first EOS, or without its PAD where it has none."""
    result = []
    for row in tokens:
        end = (row == vt.EOS).nonzero()
        result.append(row[: int(end[0]) + 1] if len(end) else row[row != vt.PAD])
    return result


@torch.inference_mode()
def generate(model: VertexDecoder, prefix: torch.Tensor, cfg: SamplingConfig,
             progress: Callable[[int, int], None] | None = None,
             should_cancel: Callable[[], bool] | None = None, progress_every: int = 16,
             evidence: Evidence | StackedEvidence | None = None, seeds: list[int] | None = None,
             rows: Callable[[int, list[int]], list[bool]] | None = None) -> list[torch.Tensor]:
    """Sample one vertex-token sequence per prefix row, all rows decoded as one batch.

    Row k samples with its own generator seeded ``cfg.seed + k`` (or ``seeds[k]``) and reads row k of
    ``evidence``: it is the sequence ``generate(model, prefix[k:k+1], cfg with seed cfg.seed + k,
    evidence of that row)`` gives.  Token for token with the ONNX Runtime decoder (its batched
    step computes each row as it does alone); with eager PyTorch up to the rounding of batched
    matrix products, which changes a sampled token only when a draw falls within ~1e-6 of a
    boundary between two tokens.

    Parameters
    ----------
    model : the decoder, or an ``onnx_decode.OrtDecoder`` wrapping it (same ``prefill``/``decode_step``), or a
        ``decode.StaticDecoder`` (which runs its own static-shape loop, drawing from counter-based noise).
    prefix : (B, M, dim) condition from ``model.condition``.
    cfg : sampling settings.
    progress : called as ``progress(step, max_vertices_so_far)`` every ``progress_every`` steps.
    should_cancel : polled at the same cadence; ``True`` raises :class:`Cancelled`.
    evidence : from ``model.point_evidence(points, normals)`` of the B shapes when the decoder was
        trained with it.
    seeds : B generator seeds, one per row (default ``cfg.seed + k``): rows of several requests decoded
        together (``fastmesh.batch``) keep the seeds they have alone.
    rows : called at the cadence of ``progress`` as ``rows(step, n_vert)`` with the B rows' vertex counts
        so far; returns B flags, True for the rows to stop now (a request of a batch that was cancelled):
        a stopped row leaves the batch as a finished one does, its sequence cut where it stopped (no EOS).

    Returns
    -------
    list of B int64 tensors: BOS ... EOS (EOS absent only if the token budget ran out).
    """
    b = prefix.shape[0]
    seeds = row_seeds(cfg, b, seeds)
    if getattr(model, "backend", None) == "static":  # models.decode: its own loop, with static shapes
        return model.generate(prefix, cfg, progress, should_cancel, progress_every, evidence, seeds, rows)
    cfg.validate()
    m, device = prefix.shape[1], prefix.device
    max_tokens = 2 * cfg.max_vertices + 2  # worst case: a block token for every vertex, plus BOS and EOS
    cache = new_cache(model, b, m + max_tokens, device, prefix.dtype)
    gens = [torch.Generator(device=device).manual_seed(seed) for seed in seeds]
    counts = evidence is not None and model.cfg.evidence_counts
    s, reading, stopped = DecodeState.start(b, device), BlockReading(), None
    logits = model.prefill(prefix, s.prev[:, None], cache)
    for step in range(1, max_tokens):
        picked = _pick(logits, s, evidence, reading, cfg, counts, gens)
        nxt = s.advance(picked)
        if step % progress_every == 0:
            stopped = _at_cadence(step, s, should_cancel, progress, rows, stopped)
        going = picked != vt.EOS
        if stopped is not None:
            going &= ~stopped[s.live]
        if not bool(going.any()):
            break
        if not bool(going.all()):  # finished rows stop costing: out of the batch and its cache
            s.keep(going, cache)
        logits = model.decode_step(nxt[s.live, None], s.block[s.live, None], m + step, cache)
    return sequences(torch.stack(s.out, dim=1))


def _pick(logits: torch.Tensor, s: DecodeState, evidence: Evidence | StackedEvidence | None, reading: BlockReading,
          cfg: SamplingConfig, counts: bool, gens: list[torch.Generator]) -> torch.Tensor:
    """(B_live,) the live rows' next tokens from their (B_live, V) logits: the evidence's bias added, the tokens
    the grammar and the pace allow, drawn by ``choose_next`` from each row's own generator."""
    logits = biased_logits(logits, s, evidence, reading, cfg, counts)
    cell_bias = None if reading.cell_bias is None else reading.cell_bias[s.live]
    return choose_next(logits.masked_fill(~allowed(s, cfg, reading), float("-inf")), cfg,
                       [gens[int(k)] for k in s.live], cell_bias)


def row_seeds(cfg: SamplingConfig, b: int, seeds: list[int] | None) -> list[int]:
    """The B rows' generator seeds: ``seeds``, or ``cfg.seed + k`` for row k; each checked against its bound."""
    seeds = [cfg.seed + k for k in range(b)] if seeds is None else list(seeds)
    if len(seeds) != b:
        raise ValueError(f"seeds: one per prefix row ({b}), got {len(seeds)}")
    for seed in seeds:
        BOUNDS["seed"].check("seed", seed)
    return seeds


def _at_cadence(step: int, s: DecodeState, should_cancel: Callable[[], bool] | None,
                progress: Callable[[int, int], None] | None, rows: Callable[[int, list[int]], list[bool]] | None,
                stopped: torch.Tensor | None) -> torch.Tensor | None:
    """What :func:`generate` does every ``progress_every`` steps: raise :class:`Cancelled` when asked, report
    progress, and return the (B,) rows to stop (``rows``' answer; ``stopped`` as it was without ``rows``)."""
    if should_cancel is not None and should_cancel():
        raise Cancelled("generation cancelled")
    if progress is not None:
        progress(step, int(s.n_vert.max()))
    if rows is None:
        return stopped
    return torch.tensor(rows(step, s.n_vert.tolist()), dtype=torch.bool, device=s.prev.device)


@torch.inference_mode()
def generate_uncached(model: VertexDecoder, prefix: torch.Tensor, max_vertices: int,
                      evidence: Evidence | None = None, cfg: SamplingConfig | None = None) -> torch.Tensor:
    """Greedy decoding without a cache (``cfg`` at temperature 0): the slow reference the cached path must equal."""
    cfg = SamplingConfig(temperature=0, max_vertices=max_vertices) if cfg is None else cfg
    if cfg.temperature != 0:
        raise ValueError("generate_uncached decodes greedily: cfg.temperature must be 0")
    reads = evidence is not None and evidence.reads_logodds
    tokens = torch.full((prefix.shape[0], 1), vt.BOS, dtype=torch.long, device=prefix.device)
    for _ in range(2 * max_vertices + 1):
        logits = model(tokens, prefix=prefix, evidence=evidence)[:, -1]
        n_vert = (tokens >= vt.OFFSET0).sum(1)
        block, offset = grammar_state(tokens)
        eos_only = n_vert >= max_vertices
        mask = grammar_mask(tokens[:, -1], block[:, -1], offset[:, -1], eos_only=eos_only)
        if reads and cfg.pace > 0:
            through = evidence.expected_through(block[:, -1], cfg.pace)
            mask[:, vt.OFFSET0:] &= ~pace_mask(through, tokens[:, -1], n_vert)[:, None]
        cell_bias = evidence.weighted_cells(block[:, -1], cfg.cell_weight) if reads else None
        nxt = choose_next(logits.masked_fill(~mask, float("-inf")), cfg, None, cell_bias)
        tokens = torch.cat([tokens, nxt[:, None]], dim=1)
        if bool(((tokens == vt.EOS).any(1)).all()):
            break
    return tokens
