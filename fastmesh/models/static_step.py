"""The vertex decoder's network as one static-shape step: a KV cache whose buffers never move, the prefill, and
``decode_one_token`` (the token through the network, its keys and values written at a position tensor), eager or
fused by ``torch.compile`` (``fused_network``).  ``decode.StaticDecoder`` runs it inside its captured step."""

from __future__ import annotations

from collections.abc import Callable

import torch

from ..tokenizer import vertex as vt
from .kv_cache import KVCache
from .layers import apply_rotary, rotary
from .vertex import VertexDecoder


class StaticCache(KVCache):
    """A :class:`KVCache` that a decode step writes by a position tensor; its buffers never move."""

    def __init__(self, model: VertexDecoder, batch: int, max_len: int, device, dtype=torch.float32):
        c = model.cfg
        super().__init__(c.depth, batch, c.heads, max_len, c.head_dim, device=device, dtype=dtype)
        self.positions = torch.arange(max_len, device=device)

    def select(self, index: torch.Tensor) -> None:
        raise RuntimeError("a static cache keeps every row (a finished one decodes PAD)")


def prefill(model: VertexDecoder, prefix: torch.Tensor, cache: StaticCache) -> torch.Tensor:
    """(B, M, dim) prefix + BOS at positions [0, M + 1) of ``cache`` -> (B, VOCAB) logits of the first token.
    The positions after are zeroed (they are masked, but a stale non-finite value would survive a mask)."""
    bos = torch.full((prefix.shape[0], 1), vt.BOS, dtype=torch.long, device=prefix.device)
    logits = model.prefill(prefix, bos, cache)
    cache.k[:, :, :, prefix.shape[1] + 1:].zero_()
    cache.v[:, :, :, prefix.shape[1] + 1:].zero_()
    return logits


def decode_one_token(model: VertexDecoder, cache: StaticCache, tokens: torch.Tensor, block: torch.Tensor,
                     pos: torch.Tensor, span: int | None = None) -> torch.Tensor:
    """(B, 1) tokens and their current blocks at position ``pos`` ((1,) int64 tensor) -> (B, VOCAB) logits.

    ``VertexDecoder.decode_step``'s maths with keys/values written at ``pos``.  Attention reads the whole
    cache under a mask of the positions up to ``pos`` (fixed shapes: what a captured graph replays), or with
    ``span`` (``pos + 1``, known to the caller) only the positions written: on a CPU the masked tail of a
    full-length cache costs as much as the rest of the step.
    """
    b = tokens.shape[0]
    x = model.embed(tokens, block)
    rope = rotary(pos, model.cfg.head_dim)
    keep = None if span is not None else (cache.positions <= pos)[None, None, None]  # (1, 1, 1, L)
    for i, layer in enumerate(model.layers):
        a = layer.attn
        h = layer.norm1(x)
        q = a.q(h).view(b, 1, a.heads, a.head_dim).transpose(1, 2)
        k, v = a.kv(h).view(b, 1, 2, a.heads, a.head_dim).permute(2, 0, 3, 1, 4)
        q, k = apply_rotary(q, *rope), apply_rotary(k, *rope)
        cache.k[i].index_copy_(2, pos, k.to(cache.k.dtype))
        cache.v[i].index_copy_(2, pos, v.to(cache.v.dtype))
        keys, values = (cache.k[i], cache.v[i]) if span is None else (cache.k[i, :, :, :span], cache.v[i, :, :, :span])
        # One query: the scores are a matrix-vector product, cheaper spelled out than through a fused kernel.
        scores = (q @ keys.transpose(-1, -2)) * a.head_dim ** -0.5  # (B, H, 1, L)
        if keep is not None:
            scores = scores.masked_fill(~keep, float("-inf"))
        y = scores.softmax(-1).to(values.dtype) @ values
        x = x + a.out(y.transpose(1, 2).reshape(b, 1, -1))
        x = x + layer.mlp(layer.norm2(x))
    return model.head(model.norm(x))[:, -1].float()


_FUSED: list = []


def fused_network() -> Callable:
    """``decode_one_token`` compiled by ``torch.compile`` (made once per process; its programs, one per batch
    and cache shape, kept by torch).  The network's step is some 250 of the eager step's 450 kernels, most of them
    tiny elementwise ones a captured graph still launches one by one; fused, a few dozen.  The sampling part
    stays as it is: it reads the request's settings as constants, so compiled it would be compiled again for
    each setting a worker meets."""
    if not _FUSED:
        _FUSED.append(torch.compile(decode_one_token, dynamic=False, fullgraph=True))
    return _FUSED[0]
