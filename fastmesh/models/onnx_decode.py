"""ONNX Runtime backend for the vertex decoder's single-token step (CPU, a batch of sequences).

Eager PyTorch spends most of a decode step in per-op dispatch (~35 small ops per
layer on 1 x 192 activations), not in arithmetic.  The same step as one ONNX graph
runs in ONNX Runtime, whose optimiser fuses the RMSNorms, Gelus and transposed
matmuls and whose executor has a far smaller per-op cost.

The graph is exported from the live model at load time (in memory, nothing is
written or downloaded).  ``OrtDecoder`` has the ``prefill``/``decode_step`` contract
of :class:`VertexDecoder`, so ``generate`` runs its unchanged sampling loop on it.

KV cache: one float32 numpy buffer (2 * depth, max_len, batch * dim), *position-major*,
so ``buf[i, :pos]`` — the past keys (even i) or values (odd i) of a layer, for every
sequence of the batch — is one contiguous block that ORT reads in place (no copy).  The
graph takes those views as inputs and returns only the step's new keys/values
(2 * depth, batch * dim), which Python writes at ``buf[:, pos]``.  Attention over the
position-major past needs per-head transposes; ORT folds them into its FusedMatMul
(strided GEMM), again without a copy.  A batch of B sequences attends as one sequence
with B * heads heads (each sequence's heads are contiguous in a position's row), so the
weights are read once per step for the whole batch.  Concatenating the new token onto
the past inside the graph, or slicing a head-major buffer, would copy the whole cache
every token (~19 MB at 2000 positions).

Prefill stays in eager PyTorch (same weights, results copied into the buffer once), one
sequence at a time, so that each sequence of a batch starts from exactly the keys and
values it has when decoded alone.
"""

from __future__ import annotations

import io
import logging
import math
import os
import warnings
from collections.abc import Collection

import numpy as np
import torch
from torch import nn

from ..params import GenerateParams
from ..tokenizer import vertex as vt
from .kv_cache import KVCache
from .layers import apply_rotary, rotary
from .vertex import VertexDecoder

log = logging.getLogger(__name__)
DEFAULT_CANDIDATES = GenerateParams().candidates  # batch size of the default decoding, exported at load


def _rms(norm: nn.Module, x: torch.Tensor) -> torch.Tensor:
    # F.rms_norm has no ONNX symbolic below opset 23; this form is fused by ORT
    # into SimplifiedLayerNormalization.
    return x * torch.rsqrt(x.pow(2).mean(-1, keepdim=True) + norm.eps) * norm.weight


class _Step(nn.Module):
    """``VertexDecoder.decode_step`` for a batch of B sequences at one position, written for export.

    Same weights and the same maths as the eager path; the differences are the cache
    layout (see the module docstring), a split softmax (past scores, then the new
    token's score) so the past is never concatenated, and q/kv projections in one matmul.
    """

    def __init__(self, model: VertexDecoder):
        super().__init__()
        self.m = model
        self.heads, self.head_dim = model.cfg.heads, model.cfg.head_dim
        # One (3 * dim, dim) projection per layer: q rows, then the kv rows (k then v).
        self.qkv = nn.ParameterList([nn.Parameter(torch.cat([blk.attn.q.weight, blk.attn.kv.weight]).detach(),
                                                  requires_grad=False) for blk in model.layers])

    def forward(self, tokens, block, cos, sin, *past):
        m, h, d = self.m, self.heads, self.head_dim
        x = m.embed(tokens, block)[:, 0]  # (B, dim), grammar-derived block/cell embeddings included
        scale = 1.0 / math.sqrt(d)
        new = []
        for i, blk in enumerate(m.layers):
            # (B, 3 * dim) -> (3, B * h, 1, d): the batch's heads side by side, as the cache holds them
            qkv = (_rms(blk.norm1, x) @ self.qkv[i].t()).view(-1, 3, h, d).transpose(0, 1).reshape(3, -1, 1, d)
            qk = apply_rotary(qkv[:2], cos, sin)  # rotary at this step's position, q and k at once
            q, k, v = qk[0], qk[1], qkv[2]  # (B * h, 1, d)
            past_k = past[2 * i].view(past[2 * i].shape[0], -1, d)  # (P, B * h, d), position-major
            past_v = past[2 * i + 1].view(past[2 * i + 1].shape[0], -1, d)
            s_past = q @ past_k.permute(1, 2, 0)  # (B * h, 1, P): FusedMatMul(transBatchB, transB) in ORT
            s_new = (q * k).sum(-1, keepdim=True)  # (B * h, 1, 1)
            p = (torch.cat([s_past, s_new], dim=-1) * scale).softmax(-1)
            y = p[..., :-1] @ past_v.permute(1, 0, 2) + p[..., -1:] * v  # (B * h, 1, d)
            x = x + blk.attn.out(y.reshape(-1, h * d))
            x = x + blk.mlp(_rms(blk.norm2, x))
            new += [k.reshape(1, -1), v.reshape(1, -1)]
        return m.head(_rms(m.norm, x)), torch.cat(new)  # (B, VOCAB), (2 * depth, B * dim)


class NumpyCache:
    """Position-major KV buffer (2 * depth, max_len, slots * dim) and the rotary tables for its positions.

    ``rows`` maps the sequences still decoding to their slots (column blocks of the buffer).  A
    finished sequence's slot stays in the buffer, computed and ignored, until the batch can move to
    a graph with fewer slots (``sizes``: the slot counts the decoder has a graph for).
    """

    def __init__(self, n: int, max_len: int, dim: int, head_dim: int, batch: int = 1,
                 sizes: Collection[int] = (1,)):
        self.buf = np.zeros((n, max_len, batch * dim), dtype=np.float32)
        cos, sin = rotary(torch.arange(max_len), head_dim)  # the eager path's own tables
        self.cos, self.sin = cos.numpy(), sin.numpy()
        self.max_len, self.dim, self.slots, self.sizes = max_len, dim, batch, sizes
        self.rows = np.arange(batch)
        self.length = 0

    def select(self, index: torch.Tensor) -> None:
        """Keep only the sequences ``index`` (B',) of those decoding, in that order: drops finished ones.

        The buffer shrinks to the fewest slots a graph exists for (copying the kept sequences once);
        until then the finished sequences' slots just stop being read.
        """
        rows = self.rows[np.asarray(index.cpu() if isinstance(index, torch.Tensor) else index, dtype=np.int64)]
        slots = min(s for s in self.sizes if s >= len(rows))
        if slots < self.slots:
            n, t = self.buf.shape[0], self.length
            buf = np.zeros((n, self.max_len, slots * self.dim), dtype=np.float32)
            kept = self.buf[:, :t].reshape(n, t, self.slots, self.dim)[:, :, rows].reshape(n, t, -1)
            buf[:, :t, :kept.shape[-1]] = kept
            self.buf, self.slots, rows = buf, slots, np.arange(len(rows))
        self.rows = rows


class OrtDecoder:
    """Runs a :class:`VertexDecoder`'s decode steps in ONNX Runtime (CPU, float32); eager otherwise.

    One graph per batch size, each with static shapes: ONNX Runtime's optimiser fuses more in a
    static graph, and a row of a static batch is computed bit for bit as the batch-1 graph computes
    it (a graph with a dynamic batch axis rounds differently), so a sequence decodes to the same
    tokens in any batch.  ``batches`` are exported at once; another size on its first use.
    """

    backend = "onnx"

    def __init__(self, model: VertexDecoder, threads: int | None = None,
                 batches: Collection[int] = (1, DEFAULT_CANDIDATES)):
        self.model = model.eval()
        self.cfg = model.cfg
        self.n = 2 * self.cfg.depth
        self.threads = threads or torch.get_num_threads()
        self.past_names = [f"past{i}" for i in range(self.n)]
        self.sessions: dict[int, object] = {}  # batch size -> ORT session
        for b in sorted({1, *batches}):
            self._session(b)

    def _session(self, batch: int):
        """The ORT session of the decode step for ``batch`` sequences (exported on first use)."""
        if batch in self.sessions:
            return self.sessions[batch]
        import onnxruntime as ort

        step = _Step(self.model).eval()
        p = 7  # example past length; the position axis is dynamic
        args = (torch.zeros(batch, 1, dtype=torch.long), torch.zeros(batch, 1, dtype=torch.long),
                *rotary(torch.tensor([p]), self.cfg.head_dim),
                *(torch.zeros(p, batch * self.cfg.dim) for _ in range(self.n)))
        f = io.BytesIO()
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the TorchScript exporter's deprecation notice
            # dynamo=False: the TorchScript exporter needs only `onnx`, not onnxscript, and
            # handles this small static graph fine.
            torch.onnx.export(step, args, f, input_names=["tokens", "block", "cos", "sin", *self.past_names],
                              output_names=["logits", "new_kv"], opset_version=17, dynamo=False,
                              dynamic_axes={n: {0: "past"} for n in self.past_names})
        so = ort.SessionOptions()
        so.intra_op_num_threads = self.threads
        so.inter_op_num_threads = 1
        so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        so.log_severity_level = 3
        self.sessions[batch] = ort.InferenceSession(f.getvalue(), so, providers=["CPUExecutionProvider"])
        return self.sessions[batch]

    # ------------------------------------------------------------------ the VertexDecoder contract

    def new_cache(self, batch: int, max_len: int, device, dtype):
        if torch.device(device).type != "cpu" or dtype != torch.float32:
            return KVCache(self.cfg.depth, batch, self.cfg.heads, max_len, self.cfg.head_dim, device=device,
                           dtype=dtype)
        self._session(batch)
        return NumpyCache(self.n, max_len, self.cfg.dim, self.cfg.head_dim, batch=batch, sizes=self.sessions.keys())

    def prefill(self, prefix: torch.Tensor, tokens: torch.Tensor, kv_cache) -> torch.Tensor:
        if isinstance(kv_cache, KVCache):
            return self.model.prefill(prefix, tokens, kv_cache)
        # Eager prefill (one call per sequence and generation) into a cache just long enough,
        # then re-lay its keys/values position-major: (layer, 1, h, T, d) -> (T, h * d) in the
        # sequence's slot of the buffer.
        t, dim = prefix.shape[1] + tokens.shape[1], self.cfg.dim
        logits = []
        for i, slot in enumerate(kv_cache.rows):
            tmp = KVCache(self.cfg.depth, 1, self.cfg.heads, t, self.cfg.head_dim)
            logits.append(self.model.prefill(prefix[i:i + 1], tokens[i:i + 1], tmp))
            kv = torch.stack([tmp.k[:, 0], tmp.v[:, 0]], dim=1)  # (layer, 2, h, T, d)
            kv_cache.buf[:, :t, slot * dim:(slot + 1) * dim] = kv.permute(0, 1, 3, 2, 4).reshape(self.n, t, dim).numpy()
        kv_cache.length = t
        return torch.cat(logits)

    def decode_step(self, tokens: torch.Tensor, block: torch.Tensor, pos: int, kv_cache) -> torch.Tensor:
        if isinstance(kv_cache, KVCache):
            return self.model.decode_step(tokens, block, pos, kv_cache)
        if pos >= kv_cache.max_len:
            raise IndexError(f"KV cache full: position {pos + 1} > {kv_cache.max_len}")
        rows, slots = kv_cache.rows, kv_cache.slots
        tok = np.full((slots, 1), vt.PAD, dtype=np.int64)  # a finished sequence's slot decodes PAD, unread
        blk = np.zeros((slots, 1), dtype=np.int64)
        tok[rows], blk[rows] = tokens.numpy(), block.numpy()
        feed = {"tokens": tok, "block": blk, "cos": kv_cache.cos[pos:pos + 1], "sin": kv_cache.sin[pos:pos + 1]}
        for i, name in enumerate(self.past_names):
            feed[name] = kv_cache.buf[i, :pos]  # contiguous view: passed to ORT without a copy
        logits, new = self._session(slots).run(None, feed)
        kv_cache.buf[:, pos] = new
        kv_cache.length = pos + 1
        return torch.from_numpy(logits if len(rows) == slots and (rows == np.arange(slots)).all() else logits[rows])


def _check(dec: OrtDecoder, atol: float = 1e-3) -> None:
    """One step on random input through both backends, with each exported graph (batch size); raise if
    the logits disagree."""
    cfg, m = dec.cfg, dec.model
    g = torch.Generator().manual_seed(0)
    for b in sorted(dec.sessions):
        prefix = torch.randn(b, 5, cfg.dim, generator=g)
        bos = torch.full((b, 1), 1, dtype=torch.long)
        # Offset tokens in varied blocks, and a block token.
        tok = torch.randint(vt.OFFSET0, vt.VOCAB_SIZE, (b, 1), generator=g)
        blk = torch.randint(0, vt.N_BLOCKS, (b, 1), generator=g)
        tok[-1], blk[-1] = vt.BLOCK0 + int(blk[-1]), blk[-1]
        ref_cache = KVCache(cfg.depth, b, cfg.heads, 8, cfg.head_dim)
        ort_cache = dec.new_cache(b, 8, "cpu", torch.float32)
        with torch.inference_mode():
            m.prefill(prefix, bos, ref_cache)
            dec.prefill(prefix, bos, ort_cache)
            err = (m.decode_step(tok, blk, 6, ref_cache) - dec.decode_step(tok, blk, 6, ort_cache)).abs().max()
        if not err <= atol:
            raise RuntimeError(f"ONNX decode step (batch {b}) differs from eager by {float(err):.2e}")


def choose_decoder(model: VertexDecoder, device: torch.device | str, threads: int | None = None):
    """The decoder ``generate`` should run: an :class:`OrtDecoder`, a ``decode.StaticDecoder`` or ``model`` itself.

    ``FASTMESH_DECODER`` = ``onnx`` | ``torch`` | ``static`` | ``auto`` (default: static shapes with the step
    captured as a CUDA graph on CUDA, onnx on CPU when onnxruntime imports: on a CPU the static loop is slower,
    ``benchmarks/decode_paths.py``).  ``threads``: ONNX Runtime's threads (default torch's count).  Any failure
    to export or to match eager logs a warning and falls back to eager: a worker never dies for want of the fast
    path.
    """
    want = os.environ.get("FASTMESH_DECODER", "auto").strip().lower() or "auto"
    if want not in ("auto", "onnx", "torch", "static"):
        log.warning("FASTMESH_DECODER=%r is not auto|onnx|torch|static; using auto", want)
        want = "auto"
    kind = torch.device(device).type
    if want == "static" or (want == "auto" and kind == "cuda"):
        from .decode import StaticDecoder

        return StaticDecoder(model)
    if want == "torch" or kind != "cpu":
        return model
    try:
        dec = OrtDecoder(model, threads=threads)
        _check(dec)
        return dec
    except ImportError as e:
        (log.warning if want == "onnx" else log.info)("ONNX decoder unavailable (%s); using eager torch", e)
    except Exception as e:  # noqa: BLE001 - any exporter/runtime failure means: run eager
        log.warning("ONNX decoder export failed (%s: %s); using eager torch", type(e).__name__, e)
    return model
