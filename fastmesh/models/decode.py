"""Static-shape vertex decoding, in gpt-fast's shape: a decode step that can be captured as one CUDA graph.

``generate.generate`` is bound by Python and kernel launches on a GPU: each token reads values back to the
host (the grammar state as lists, NaN checks, the draw of a ``torch.Generator``) and finished rows leave
the batch, so no two steps have the same shapes.  Here everything a step needs lives in preallocated
device tensors of fixed shapes, and one step is

    sample  (evidence bias, count bias, grammar / pace mask, two-step Gumbel draw: ``sampling``)
    update  (grammar state, the token written at ``out[:, step]``)
    decode_one_token  (the token through the network, its keys/values written at ``prefix + step``: ``static_step``)

with the step counter itself a device tensor, so the same launches serve every step.  On CUDA the step is
captured once per batch shape (``torch.cuda.CUDAGraph``; batches padded to a power of two) and replayed;
elsewhere it runs eagerly, the same code.  The host reads back one small tensor every ``CHECK_EVERY`` steps
(all rows finished? a row with no finite logit? the vertex count for progress) and polls ``should_cancel``
there.

The KV cache (``StaticCache``) is allocated at full length (prefix + 2 * max_vertices + 2 positions); a
step writes its position with ``index_copy_`` and attends to the whole buffer under a mask of the positions
written (uncaptured on a CPU, to those positions only: ``decode_one_token``'s ``span``).  Finished rows stay
in the batch, decoding PAD, so shapes never change.  On CUDA the evidence's bias of every block is tabled
once per call and a step reads its row with one gather (``bias_table``).

Draws differ from ``generate`` by construction (counter-based noise instead of ``torch.Generator``): row k
samples from the hash of seed ``cfg.seed + k`` and the step, the same alone or in any batch.  At
temperature 0 both loops take the same argmax.
"""

from __future__ import annotations

import logging
import os
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import astuple

import torch

from ..params import SamplingConfig
from ..tokenizer import vertex as vt
from .evidence import Evidence, _block
from .generate import Cancelled, StackedEvidence, pace_mask, sequences
from .sampling import choose_static, seed_key
from .static_step import StaticCache, decode_one_token, fused_network, prefill
from .vertex import VertexDecoder, add_count_bias, grammar_mask

log = logging.getLogger(__name__)
CHECK_EVERY = 16  # steps between two reads of the loop's state by the host
MAX_GRAPHS = 8  # captured batch shapes kept per decoder (batch sizes 1, 2, 4, ... 128)
# Evidence attributes with one row per shape (the others are shared tables and index helpers).
_ROWS = ("levels", "occ_incl", "occ_excl", "spread", "logodds", "given", "cell_expected", "cell_cum", "cell_incl",
         "cell_excl")


def _rows_of(ev: Evidence | StackedEvidence) -> list[Evidence]:
    return ev.rows if isinstance(ev, StackedEvidence) else [ev]


def stack_evidence(rows: Sequence[Evidence]) -> Evidence:
    """One :class:`Evidence` holding the rows of ``rows`` (each computed alone) in order: row i reads what
    ``rows``' i-th row reads (the per-step readings are gathers and lookups, row by row)."""
    out = object.__new__(Evidence)
    out.__dict__.update(rows[0].__dict__)
    for name in _ROWS:
        first = getattr(rows[0], name, None)
        if isinstance(first, list):
            setattr(out, name, [torch.cat(parts) for parts in zip(*(getattr(e, name) for e in rows), strict=True)])
        elif first is not None:
            setattr(out, name, torch.cat([getattr(e, name) for e in rows]))
    return out


def _copy_evidence(dst: Evidence, src: Evidence) -> None:
    """Copy ``src``'s rows into ``dst``'s tensors of the same shapes, in place (a captured graph reads them)."""
    for name in _ROWS:
        a, b = getattr(dst, name, None), getattr(src, name, None)
        for x, y in zip(a if isinstance(a, list) else [a], b if isinstance(b, list) else [b], strict=True):
            if x is not None:
                x.copy_(y)


def bias_table(evidence: Evidence, out: torch.Tensor) -> torch.Tensor:
    """Fill ``out`` (B, 1 + N_BLOCKS, VOCAB) with ``evidence.logit_bias`` of every current block (row j: block
    j - 1, so row 0 is "no block yet"): a step then reads its bias with one gather.  One shape at a time (the
    int64 indices of all blocks of one shape are 16 MB)."""
    blocks = torch.arange(-1, vt.N_BLOCKS, device=out.device)
    for i in range(out.shape[0]):
        rows = torch.full_like(blocks, i)
        out[i] = torch.cat(evidence._sequence_rows(rows, blocks) + [evidence._offset_rows(rows, blocks)], dim=-1)
    return out


def masked_logits(logits: torch.Tensor, state: dict, cfg: SamplingConfig, evidence: Evidence | None,
                  counts: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
    """(B, VOCAB) decoder logits -> the logits ``generate`` samples from (evidence and count bias added,
    grammar and pace masks applied) and the (B, 4096) cell weight on the offsets (or None)."""
    prev, block, offset, n_vert = state["prev"], state["block"], state["offset"], state["n_vert"]
    cell_bias = through = None
    if evidence is not None:
        rows, blk = state["rows"], _block(block)
        if "bias" in state:  # the table of every block: one gather
            logits = logits + state["bias"][rows, blk + 1]
        else:  # the current blocks' rows of it, as Evidence.logit_bias computes them
            logits = logits + torch.cat(evidence._sequence_rows(rows, blk) + [evidence._offset_rows(rows, blk)], -1)
        if counts:
            eos, stay = evidence.count_bias(block[:, None], offset[:, None], n_vert[:, None],
                                            state["n_in_block"][:, None])
            logits = add_count_bias(logits, eos[:, 0], stay[:, 0])
        if evidence.reads_logodds:
            cell_bias = evidence.weighted_cells(block, cfg.cell_weight)
            through = evidence.expected_through(block, cfg.pace)
    mask = grammar_mask(prev, block, offset, eos_only=n_vert >= cfg.max_vertices)
    if through is not None and cfg.pace > 0:
        mask[:, vt.OFFSET0:] &= ~pace_mask(through, prev, n_vert)[:, None]
    return logits.masked_fill(~mask, float("-inf")), cell_bias


def advance(state: dict, nxt: torch.Tensor) -> None:
    """Write token ``nxt`` (B,) at ``out[:, step]`` and move the grammar state past it, in place."""
    state["out"].index_copy_(1, state["step"], nxt[:, None])
    is_block = (nxt >= vt.BLOCK0) & (nxt < vt.OFFSET0)
    is_off = nxt >= vt.OFFSET0
    block, offset = state["block"], state["offset"]
    offset.copy_(torch.where(is_off, nxt - vt.OFFSET0, torch.where(is_block, -1, offset)))
    block.copy_(torch.where(is_block, nxt - vt.BLOCK0, block))
    state["n_vert"].add_(is_off.long())
    state["n_in_block"].copy_(torch.where(is_block, 0, state["n_in_block"] + is_off.long()))
    state["prev"].copy_(nxt)
    state["done"] |= (nxt == vt.EOS) | (nxt == vt.PAD)


class _Batch:
    """The static buffers of one batch shape, and its step (captured as a graph on CUDA)."""

    def __init__(self, model: VertexDecoder, cfg: SamplingConfig, batch: int, m: int, device, dtype,
                 evidence: Evidence | None, window: bool, table: bool, compiled: bool = False):
        self.model, self.cfg, self.m, self.window = model, cfg, m, window
        self.max_tokens = 2 * cfg.max_vertices + 2  # a block token for every vertex, plus BOS and EOS
        # The network's step fused (``fused_network``): its cache as long as the decoder's own limit asks, so the
        # compiled program depends on the batch size alone, whatever a request's vertex budget.
        self.fused = fused_network() if compiled else None
        length = m + (2 * max(model.cfg.max_vertices, cfg.max_vertices) + 2 if compiled else self.max_tokens)
        self.cache = StaticCache(model, batch, length, device, dtype)
        self.evidence = evidence
        self.counts = evidence is not None and model.cfg.evidence_counts
        z = dict(dtype=torch.long, device=device)
        self.state = {"rows": torch.arange(batch, device=device), "step": torch.ones(1, **z),
                      "keys": torch.zeros(batch, **z), "out": torch.full((batch, self.max_tokens), vt.PAD, **z),
                      "prev": torch.zeros(batch, **z), "block": torch.zeros(batch, **z),
                      "offset": torch.zeros(batch, **z), "n_vert": torch.zeros(batch, **z),
                      "n_in_block": torch.zeros(batch, **z),
                      "done": torch.zeros(batch, dtype=torch.bool, device=device),
                      "stuck": torch.zeros(batch, dtype=torch.bool, device=device),
                      "logits": torch.zeros(batch, vt.VOCAB_SIZE, device=device)}
        if evidence is not None and table:
            self.state["bias"] = torch.zeros(batch, 1 + vt.N_BLOCKS, vt.VOCAB_SIZE, device=device)
        self.graph = None

    def reset(self, prefix: torch.Tensor, keys: Sequence[int], evidence: Evidence | None,
              live: int) -> None:
        """Start a new generation of ``prefix`` (B, M, dim): prefill, state at BOS, this call's evidence; the rows
        from ``live`` on are padding, finished from the start."""
        s = self.state
        if evidence is not None:
            _copy_evidence(self.evidence, evidence)
            if "bias" in s:
                bias_table(evidence, s["bias"])
        s["logits"].copy_(prefill(self.model, prefix, self.cache))
        s["keys"].copy_(torch.tensor(list(keys), dtype=torch.long))
        s["step"].fill_(1)
        s["out"].fill_(vt.PAD)
        s["out"][:, 0] = vt.BOS
        s["prev"].fill_(vt.BOS)
        for name in ("block", "offset"):
            s[name].fill_(-1)
        for name in ("n_vert", "n_in_block", "done", "stuck"):
            s[name].zero_()
        s["done"][live:] = True

    def step(self, span: int | None = None) -> None:
        """Choose the token of ``step`` for every row, advance, and run it through the decoder (attending to the
        first ``span`` positions of the cache, or to all of them under a mask)."""
        s = self.state
        logits, cell_bias = masked_logits(s["logits"], s, self.cfg, self.evidence, self.counts)
        nxt, stuck = choose_static(logits, self.cfg, s["keys"], s["step"], cell_bias)
        s["stuck"] |= stuck & ~s["done"]
        nxt = torch.where(s["done"], vt.PAD, nxt)  # a row ended (EOS) or stopped by the caller takes PAD
        advance(s, nxt)
        network = self.fused or decode_one_token
        s["logits"].copy_(network(self.model, self.cache, nxt[:, None], s["block"][:, None], self.m + s["step"], span))
        s["step"].add_(1)

    def capture(self) -> None:
        """Record :meth:`step` as a CUDA graph (after warm-up steps on a side stream, whose effect on the state is
        undone: the caller resets before the first replay)."""
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):
            for _ in range(2):
                self.step()
        torch.cuda.current_stream().wait_stream(side)
        self.graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(self.graph):  # a private memory pool: graphs of other shapes never share it
            self.step()

    def run_step(self, step: int) -> None:
        """Step ``step`` (the host's count, equal to the state's): the graph's replay, or the step run eagerly."""
        if self.graph is not None:
            self.graph.replay()
        else:
            self.step(self.m + step + 1 if self.window else None)


class StaticDecoder:
    """Runs ``generate`` with static shapes for a :class:`VertexDecoder` (``backend = "static"``).

    ``capture``: record each batch shape's step as a CUDA graph (default: on CUDA).  ``window``: uncaptured
    steps attend to the positions written only (default: on a CPU), not to the whole cache under a mask
    (the same tokens, up to rounding).  ``table``: the evidence's bias of every block is made once per call,
    (B, 513, VOCAB), and a step reads its row (default: on CUDA, where it replaces some 40 launches a step by
    one; on a CPU making it costs more than reading the current blocks' rows at every step).  The buffers and graph
    of the last ``MAX_GRAPHS`` shapes (batch, prefix, vertex budget, sampling settings) are kept, so a
    worker's jobs reuse them; each job's prefix, evidence and seeds are copied into them.  ``compiled``: the
    network's step fused by ``torch.compile`` (``fused_network``) before it is captured (default: with capture
    where ``FASTMESH_COMPILE=1``): some seconds once per batch size and process (inductor's cache on disk shortens
    the next process's), then fewer kernels a step.  Where compiling fails the step runs as it is.
    """

    backend = "static"

    def __init__(self, model: VertexDecoder, capture: bool | None = None, window: bool | None = None,
                 table: bool | None = None, compiled: bool | None = None):
        self.model = model.eval()
        self.cfg = model.cfg
        device = next(model.parameters()).device
        self.capture = device.type == "cuda" if capture is None else capture
        if self.capture and device.type != "cuda":
            raise ValueError("CUDA graph capture needs the decoder on a CUDA device")
        self.window = device.type == "cpu" if window is None else window
        self.table = device.type == "cuda" if table is None else table
        if compiled is None:  # off until a card has measured it (benchmarks/decode_paths.py: static_graph_fused)
            compiled = self.capture and os.environ.get("FASTMESH_COMPILE", "0").strip() in ("1", "true", "yes")
        self.compiled = compiled
        self._batches: OrderedDict[tuple, _Batch] = OrderedDict()

    def _batch(self, prefix: torch.Tensor, cfg: SamplingConfig, evidence: Evidence | None) -> tuple[_Batch, bool]:
        """The static buffers for this call's shapes, and whether they are new."""
        key = (tuple(prefix.shape), prefix.dtype, astuple(SamplingConfig(**{**cfg.__dict__, "seed": 0})),
               evidence is not None)
        if key in self._batches:
            self._batches.move_to_end(key)
            return self._batches[key], False
        if len(self._batches) >= MAX_GRAPHS:
            self._batches.popitem(last=False)
        own_ev = None if evidence is None else stack_evidence([evidence])
        b = _Batch(self.model, cfg, prefix.shape[0], prefix.shape[1], prefix.device, prefix.dtype, own_ev,
                   self.window and not self.capture and not self.compiled, self.table, self.compiled)
        self._batches[key] = b
        return b, True

    @torch.inference_mode()
    def generate(self, prefix: torch.Tensor, cfg: SamplingConfig, progress: Callable[[int, int], None] | None = None,
                 should_cancel: Callable[[], bool] | None = None, progress_every: int = CHECK_EVERY,
                 evidence: Evidence | StackedEvidence | None = None, seeds: Sequence[int] | None = None,
                 rows: Callable[[int, list[int]], list[bool]] | None = None) -> list[torch.Tensor]:
        """``generate.generate``'s contract, decoded with static shapes: row k samples with seed ``cfg.seed + k``
        (or ``seeds[k]``).  The host reads the loop's state every ``progress_every`` steps: then ``progress``,
        ``should_cancel`` and ``rows`` run (``rows(step, n_vert)`` returns a flag per row, True to stop it there:
        its sequence ends without EOS), and the loop stops once every row has finished."""
        cfg.validate()
        b = prefix.shape[0]
        seeds = [cfg.seed + k for k in range(b)] if seeds is None else list(seeds)
        if len(seeds) != b:
            raise ValueError(f"{len(seeds)} seeds for {b} rows")
        batch = self._start(prefix, cfg, evidence, seeds)
        s = batch.state
        for step in range(1, batch.max_tokens):
            batch.run_step(step)
            if step % progress_every == 0 or step == batch.max_tokens - 1:
                read = torch.cat([torch.stack([s["done"].all(), s["stuck"].any()]).long(), s["n_vert"][:b]]).tolist()
                if read[1]:
                    raise FloatingPointError("the vertex decoder's logits allow no token (none is finite)")
                if should_cancel is not None and should_cancel():
                    raise Cancelled("generation cancelled")
                if progress is not None:
                    progress(step, max(read[2:]))
                if rows is not None:
                    s["done"][:b] |= torch.tensor(rows(step, read[2:]), dtype=torch.bool).to(s["done"].device)
                    read[0] = bool(s["done"].all())
                if read[0]:
                    break
        return sequences(s["out"][:b].to("cpu", copy=True))  # a copy: the buffer is the next call's

    def _start(self, prefix: torch.Tensor, cfg: SamplingConfig, evidence: Evidence | StackedEvidence | None,
               seeds: list[int]) -> _Batch:
        """The static batch of this call, reset to its inputs (captured first where it is new).

        With capture the rows are padded to a power of two (copies of row 0, finished from the start), so the
        batches of a worker, which vary in size, share a few graphs.
        """
        b = prefix.shape[0]
        pad = (1 << (b - 1).bit_length()) - b if self.capture else 0
        prefix = torch.cat([prefix, prefix[:1].expand(pad, -1, -1)]) if pad else prefix
        ev = None if evidence is None else stack_evidence(_rows_of(evidence) + [_rows_of(evidence)[0]] * pad)
        batch, new = self._batch(prefix, cfg, ev)
        keys = [seed_key(x) for x in seeds] + [0] * pad
        batch.reset(prefix, keys, ev, live=b)
        if new and batch.fused is not None and not self.capture:
            self._fuse(batch)
        if new and self.capture:
            self._capture(batch)
        if new:
            batch.reset(prefix, keys, ev, live=b)
        return batch

    @staticmethod
    def _fuse(batch: _Batch) -> None:
        """Compile the network's step (the batch's first step, whose effect on the state the caller resets); where
        compiling fails, run it eagerly."""
        try:
            batch.step()
        except Exception as e:  # noqa: BLE001 - any compiler failure: the same step, unfused
            log.warning("compiling the decode step failed (%s: %s); running it uncompiled", type(e).__name__, e)
            batch.fused = None

    @staticmethod
    def _capture(batch: _Batch) -> None:
        """Capture the step (fused where it compiles); where capture fails, the same steps run eagerly."""
        if batch.fused is not None:
            try:
                batch.capture()
                return
            except Exception as e:  # noqa: BLE001 - a compiler or capture failure: capture the unfused step
                log.warning("capturing the compiled decode step failed (%s: %s); capturing it uncompiled",
                            type(e).__name__, e)
                batch.fused, batch.graph = None, None
        try:
            batch.capture()
        except RuntimeError as e:  # an op the graph cannot hold: the same steps, run eagerly
            log.warning("CUDA graph capture of the decode step failed (%s); decoding without it", e)
            batch.graph = None

