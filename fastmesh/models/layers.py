"""Transformer building blocks shared by every FastMesh network.

Pre-norm blocks with RMSNorm, rotary position embeddings (so sequence length is not
capped by a table) and ``scaled_dot_product_attention`` (flash / memory-efficient
kernels where PyTorch has them, plain math on CPU).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from ..tokenizer.grid import LEVELS


class RMSNorm(nn.Module):
    def __init__(self, dim: int, eps: float = 1e-6):
        super().__init__()
        self.eps = eps
        self.weight = nn.Parameter(torch.ones(dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.rms_norm(x, (x.shape[-1],), self.weight, self.eps)


def rotary(positions: torch.Tensor, head_dim: int, base: float = 10000.0) -> tuple[torch.Tensor, torch.Tensor]:
    """cos/sin tables (T, head_dim) for integer ``positions`` (T,), in the rotate-half layout."""
    inv = 1.0 / (base ** (torch.arange(0, head_dim, 2, device=positions.device, dtype=torch.float32) / head_dim))
    ang = positions.float()[:, None] * inv[None]
    ang = torch.cat([ang, ang], dim=-1)
    return ang.cos(), ang.sin()


def apply_rotary(x: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
    """Rotate channel pairs (i, i + D/2) of x (B, H, T, D) by the angles of cos/sin (T, D)."""
    x1, x2 = x.chunk(2, dim=-1)
    rot = torch.cat([-x2, x1], dim=-1)
    return x * cos.to(x.dtype) + rot * sin.to(x.dtype)


class Attention(nn.Module):
    """Multi-head self- or cross-attention.

    ``kv_cache`` (see ``models.kv_cache.KVCache``) makes it incremental: new keys and
    values are written at ``cache_pos`` and attention runs over everything cached.
    """

    def __init__(self, dim: int, heads: int, kv_dim: int | None = None):
        super().__init__()
        assert dim % heads == 0, "dim must be divisible by heads"
        self.heads, self.head_dim = heads, dim // heads
        self.q = nn.Linear(dim, dim, bias=False)
        self.kv = nn.Linear(kv_dim or dim, 2 * dim, bias=False)
        self.out = nn.Linear(dim, dim, bias=False)

    def forward(self, x: torch.Tensor, context: torch.Tensor | None = None, mask: torch.Tensor | None = None,
                is_causal: bool = False, rope: tuple[torch.Tensor, torch.Tensor] | None = None,
                kv_cache=None, layer: int = 0, cache_pos: int = 0) -> torch.Tensor:
        b, t, _ = x.shape
        src = x if context is None else context
        q = self.q(x).view(b, t, self.heads, self.head_dim).transpose(1, 2)
        k, v = self.kv(src).view(b, src.shape[1], 2, self.heads, self.head_dim).permute(2, 0, 3, 1, 4)
        if rope is not None:
            q, k = apply_rotary(q, *rope), apply_rotary(k, *rope)
        if kv_cache is not None:
            k, v = kv_cache.update(layer, cache_pos, k, v)
        y = F.scaled_dot_product_attention(q, k, v, attn_mask=mask, is_causal=is_causal and mask is None)
        return self.out(y.transpose(1, 2).reshape(b, t, -1))


class MLP(nn.Module):
    def __init__(self, dim: int, mult: int = 4):
        super().__init__()
        self.fc = nn.Linear(dim, mult * dim, bias=False)
        self.proj = nn.Linear(mult * dim, dim, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.proj(F.gelu(self.fc(x), approximate="tanh"))


class Block(nn.Module):
    """Pre-norm transformer block: self-attention, optional cross-attention, MLP."""

    def __init__(self, dim: int, heads: int, cross_dim: int | None = None):
        super().__init__()
        self.norm1, self.attn = RMSNorm(dim), Attention(dim, heads)
        self.cross = None
        if cross_dim is not None:
            self.norm_c, self.cross = RMSNorm(dim), Attention(dim, heads, kv_dim=cross_dim)
        self.norm2, self.mlp = RMSNorm(dim), MLP(dim)

    def forward(self, x: torch.Tensor, context: torch.Tensor | None = None, **attn_kw) -> torch.Tensor:
        x = x + self.attn(self.norm1(x), **attn_kw)
        if self.cross is not None:
            x = x + self.cross(self.norm_c(x), context=context)
        return x + self.mlp(self.norm2(x))


class CoordEmbedding(nn.Module):
    """Embeds 7-bit cells (…, 3) as the sum of one learned table per axis.

    Factorising by axis shares statistics across the 2M possible cells, which matters
    with a few thousand training meshes.
    """

    def __init__(self, dim: int, levels: int = LEVELS):
        super().__init__()
        self.levels = levels
        self.tables = nn.ModuleList([nn.Embedding(levels, dim) for _ in range(3)])

    def forward(self, q: torch.Tensor) -> torch.Tensor:
        """(…, 3) int cells -> (…, dim); coordinates are held to ``[0, levels)`` (an index outside a table is a
        device-side assert on CUDA), which leaves cells on the grid unchanged."""
        q = q.clamp(0, self.levels - 1)
        return sum(t(q[..., i]) for i, t in enumerate(self.tables))


def fourier_features(x: torch.Tensor, n_freqs: int) -> torch.Tensor:
    """(…, 3) positions in the unit cube -> (…, 3 + 6 * n_freqs) [x, sin(2^k pi x), cos(2^k pi x)]."""
    freqs = (2.0 ** torch.arange(n_freqs, device=x.device, dtype=x.dtype)) * math.pi
    ang = (x[..., None] * freqs).flatten(-2)
    return torch.cat([x, ang.sin(), ang.cos()], dim=-1)


def init_weights(module: nn.Module, std: float = 0.02) -> None:
    """GPT-2 style initialisation: small normal weights, zero biases."""
    for m in module.modules():
        if isinstance(m, nn.Linear):
            nn.init.normal_(m.weight, std=std)
            if m.bias is not None:
                nn.init.zeros_(m.bias)
        elif isinstance(m, nn.Embedding):
            nn.init.normal_(m.weight, std=std)
