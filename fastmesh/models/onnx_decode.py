"""ONNX Runtime backend for the vertex decoder's single-token step (batch 1, CPU).

Eager PyTorch spends most of a decode step in per-op dispatch (~35 small ops per
layer on 1 x 192 activations), not in arithmetic.  The same step as one ONNX graph
runs in ONNX Runtime, whose optimiser fuses the RMSNorms, Gelus and transposed
matmuls and whose executor has a far smaller per-op cost.

The graph is exported from the live model at load time (in memory, nothing is
written or downloaded).  ``OrtDecoder`` has the ``prefill``/``decode_step`` contract
of :class:`VertexDecoder`, so ``generate`` runs its unchanged sampling loop on it.

KV cache: one float32 numpy buffer (2 * depth, max_len, dim), *position-major*, so
``buf[i, :pos]`` — the past keys (even i) or values (odd i) of a layer — is one
contiguous block that ORT reads in place (no copy).  The graph takes those views as
inputs and returns only the step's new keys/values (2 * depth, dim), which Python
writes at ``buf[:, pos]``.  Attention over the position-major past needs per-head
transposes; ORT folds them into its FusedMatMul (strided GEMM), again without a copy.
Concatenating the new token onto the past inside the graph, or slicing a head-major
buffer, would copy the whole cache every token (~19 MB at 2000 positions).

Batch > 1 and prefill stay in eager PyTorch (same weights, results copied into the
buffer once), which keeps this small; ``new_cache`` hands out a torch ``KVCache`` then.
"""

from __future__ import annotations

import io
import logging
import math
import os
import warnings

import numpy as np
import torch
from torch import nn

from .kv_cache import KVCache
from .layers import apply_rotary, rotary
from .vertex import VertexDecoder

log = logging.getLogger(__name__)


def _rms(norm: nn.Module, x: torch.Tensor) -> torch.Tensor:
    # F.rms_norm has no ONNX symbolic below opset 23; this form is fused by ORT
    # into SimplifiedLayerNormalization.
    return x * torch.rsqrt(x.pow(2).mean(-1, keepdim=True) + norm.eps) * norm.weight


class _Step(nn.Module):
    """``VertexDecoder.decode_step`` for batch 1, written for export.

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
        x = m.embed(tokens, block)[:, 0]  # (1, dim), grammar-derived block/cell embeddings included
        scale = 1.0 / math.sqrt(d)
        new = []
        for i, blk in enumerate(m.layers):
            qkv = (_rms(blk.norm1, x) @ self.qkv[i].t()).view(3, h, 1, d)
            qk = apply_rotary(qkv[:2], cos, sin)  # rotary at this step's position, q and k at once
            q, k, v = qk[0], qk[1], qkv[2]  # (h, 1, d)
            past_k = past[2 * i].view(-1, h, d)  # (P, h, d), position-major
            past_v = past[2 * i + 1].view(-1, h, d)
            s_past = q @ past_k.permute(1, 2, 0)  # (h, 1, P): FusedMatMul(transBatchB, transB) in ORT
            s_new = (q * k).sum(-1, keepdim=True)  # (h, 1, 1)
            p = (torch.cat([s_past, s_new], dim=-1) * scale).softmax(-1)
            y = p[..., :-1] @ past_v.permute(1, 0, 2) + p[..., -1:] * v  # (h, 1, d)
            x = x + blk.attn.out(y.reshape(1, h * d))
            x = x + blk.mlp(_rms(blk.norm2, x))
            new += [k.reshape(1, h * d), v.reshape(1, h * d)]
        return m.head(_rms(m.norm, x)), torch.cat(new)  # (1, VOCAB), (2 * depth, dim)


class NumpyCache:
    """Position-major KV buffer (2 * depth, max_len, dim) and the rotary tables for its positions."""

    def __init__(self, n: int, max_len: int, dim: int, head_dim: int):
        self.buf = np.zeros((n, max_len, dim), dtype=np.float32)
        cos, sin = rotary(torch.arange(max_len), head_dim)  # the eager path's own tables
        self.cos, self.sin = cos.numpy(), sin.numpy()
        self.max_len = max_len
        self.length = 0


class OrtDecoder:
    """Runs a :class:`VertexDecoder`'s decode steps in ONNX Runtime (batch 1); eager otherwise."""

    backend = "onnx"

    def __init__(self, model: VertexDecoder, threads: int | None = None):
        import onnxruntime as ort

        self.model = model.eval()
        self.cfg = model.cfg
        self.n = 2 * self.cfg.depth
        step = _Step(model).eval()
        p = 7  # example past length; the position axis is dynamic
        args = (torch.zeros(1, 1, dtype=torch.long), torch.zeros(1, 1, dtype=torch.long),
                *rotary(torch.tensor([p]), self.cfg.head_dim), *(torch.zeros(p, self.cfg.dim) for _ in range(self.n)))
        self.past_names = [f"past{i}" for i in range(self.n)]
        f = io.BytesIO()
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the TorchScript exporter's deprecation notice
            # dynamo=False: the TorchScript exporter needs only `onnx`, not onnxscript, and
            # handles this small static graph fine.
            torch.onnx.export(step, args, f, input_names=["tokens", "block", "cos", "sin", *self.past_names],
                              output_names=["logits", "new_kv"], opset_version=17, dynamo=False,
                              dynamic_axes={n: {0: "past"} for n in self.past_names})
        so = ort.SessionOptions()
        so.intra_op_num_threads = threads or torch.get_num_threads()
        so.inter_op_num_threads = 1
        so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        so.log_severity_level = 3
        self.session = ort.InferenceSession(f.getvalue(), so, providers=["CPUExecutionProvider"])

    # ------------------------------------------------------------------ the VertexDecoder contract

    def new_cache(self, batch: int, max_len: int, device, dtype):
        if batch != 1 or torch.device(device).type != "cpu" or dtype != torch.float32:
            return KVCache(self.cfg.depth, batch, self.cfg.heads, max_len, self.cfg.head_dim, device=device,
                           dtype=dtype)
        return NumpyCache(self.n, max_len, self.cfg.dim, self.cfg.head_dim)

    def prefill(self, prefix: torch.Tensor, tokens: torch.Tensor, kv_cache) -> torch.Tensor:
        if isinstance(kv_cache, KVCache):
            return self.model.prefill(prefix, tokens, kv_cache)
        # Eager prefill (one call per generation) into a cache just long enough, then
        # re-lay its keys/values position-major: (layer, 1, h, T, d) -> (T, h * d).
        t = prefix.shape[1] + tokens.shape[1]
        tmp = KVCache(self.cfg.depth, 1, self.cfg.heads, t, self.cfg.head_dim)
        logits = self.model.prefill(prefix, tokens, tmp)
        kv = torch.stack([tmp.k[:, 0], tmp.v[:, 0]], dim=1)  # (layer, 2, h, T, d)
        kv_cache.buf[:, :t] = kv.permute(0, 1, 3, 2, 4).reshape(self.n, t, self.cfg.dim).numpy()
        kv_cache.length = t
        return logits

    def decode_step(self, tokens: torch.Tensor, block: torch.Tensor, pos: int, kv_cache) -> torch.Tensor:
        if isinstance(kv_cache, KVCache):
            return self.model.decode_step(tokens, block, pos, kv_cache)
        if pos >= kv_cache.max_len:
            raise IndexError(f"KV cache full: position {pos + 1} > {kv_cache.max_len}")
        feed = {"tokens": np.ascontiguousarray(tokens.numpy()), "block": np.ascontiguousarray(block.numpy()),
                "cos": kv_cache.cos[pos:pos + 1], "sin": kv_cache.sin[pos:pos + 1]}
        for i, name in enumerate(self.past_names):
            feed[name] = kv_cache.buf[i, :pos]  # contiguous view: passed to ORT without a copy
        logits, new = self.session.run(None, feed)
        kv_cache.buf[:, pos] = new
        kv_cache.length = pos + 1
        return torch.from_numpy(logits)


def _check(dec: OrtDecoder, atol: float = 1e-3) -> None:
    """One step on random input through both backends; raise if the logits disagree."""
    cfg, m = dec.cfg, dec.model
    g = torch.Generator().manual_seed(0)
    prefix = torch.randn(1, 5, cfg.dim, generator=g)
    bos = torch.full((1, 1), 1, dtype=torch.long)
    tok, blk = torch.tensor([[m.tok_emb.num_embeddings - 1]]), torch.tensor([[3]])  # an offset token
    ref_cache = KVCache(cfg.depth, 1, cfg.heads, 8, cfg.head_dim)
    ort_cache = dec.new_cache(1, 8, "cpu", torch.float32)
    with torch.inference_mode():
        m.prefill(prefix, bos, ref_cache)
        dec.prefill(prefix, bos, ort_cache)
        err = (m.decode_step(tok, blk, 6, ref_cache) - dec.decode_step(tok, blk, 6, ort_cache)).abs().max()
    if not err <= atol:
        raise RuntimeError(f"ONNX decode step differs from eager by {float(err):.2e}")


def choose_decoder(model: VertexDecoder, device: torch.device | str):
    """The decoder ``generate`` should run: an :class:`OrtDecoder` or ``model`` itself.

    ``FASTMESH_DECODER`` = ``onnx`` | ``torch`` | ``auto`` (default: onnx on CPU when
    onnxruntime imports).  Any failure to export or to match eager logs a warning and
    falls back to eager: a worker never dies for want of the fast path.
    """
    want = os.environ.get("FASTMESH_DECODER", "auto").strip().lower() or "auto"
    if want not in ("auto", "onnx", "torch"):
        log.warning("FASTMESH_DECODER=%r is not auto|onnx|torch; using auto", want)
        want = "auto"
    if want == "torch" or torch.device(device).type != "cpu":
        return model
    try:
        dec = OrtDecoder(model)
        _check(dec)
        return dec
    except ImportError as e:
        (log.warning if want == "onnx" else log.info)("ONNX decoder unavailable (%s); using eager torch", e)
    except Exception as e:  # noqa: BLE001 - any exporter/runtime failure means: run eager
        log.warning("ONNX decoder export failed (%s: %s); using eager torch", type(e).__name__, e)
    return model
