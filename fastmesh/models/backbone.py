"""Bidirectional transformer over a set of 7-bit vertices, conditioned by a latent prefix.

Shared by the fidelity enhancer and the face model.  The sequence is

    [latent_1 .. latent_M] [vertex_1 .. vertex_N]

Vertices carry no position embedding, only their cell (a learned table per axis plus
Fourier features of the cell centre), so the network is equivariant to the order of the
vertices: order matters only through an explicit attention mask (prediction filtering).
The prefix rows attend to the prefix only, so the condition is the same whatever vertices
or mask follow, and every vertex always sees the whole prefix.

Optional geometric attention bias (``distance_bias``): between vertices, each head adds
``-slope * |c_i - c_j|`` (cell-centre distance, unit cube) to its attention scores, with
one learned slope per layer and head, initialised from local (steep) to global (flat) as
in ALiBi.  Mesh connectivity is local, and without the bias attention has to discover
locality from absolute embeddings, which costs many training steps.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from ..tokenizer.grid import dequantize
from .encoder import EncoderConfig, PointEncoder
from .layers import Block, CoordEmbedding, RMSNorm, fourier_features


def full_attention_mask(valid: torch.Tensor, n_prefix: int, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Boolean SDPA mask (B, 1, M+N, M+N) for prefix + vertices (True = may attend).

    Parameters
    ----------
    valid : (B, N) bool, False on padding.
    n_prefix : M.
    mask : (B, N, N) bool among vertices (row attends column), or None for all pairs.
        The diagonal is always allowed, so no row is ever empty.
    """
    b, n = valid.shape
    m = n_prefix
    dev = valid.device
    vv = valid[:, None, :].expand(b, n, n)
    if mask is not None:
        vv = vv & mask
    vv = vv | torch.eye(n, dtype=torch.bool, device=dev)[None]
    top = torch.cat([torch.ones(b, m, m, dtype=torch.bool, device=dev),
                     torch.zeros(b, m, n, dtype=torch.bool, device=dev)], dim=2)
    bottom = torch.cat([torch.ones(b, n, m, dtype=torch.bool, device=dev), vv], dim=2)
    return torch.cat([top, bottom], dim=1)[:, None]


class VertexSetBackbone(nn.Module):
    """Point encoder + prefix + bidirectional blocks; returns per-vertex features."""

    def __init__(self, dim: int, depth: int, heads: int, encoder: EncoderConfig, n_freqs: int,
                 distance_bias: bool = False):
        super().__init__()
        self.n_freqs = n_freqs
        self.encoder = PointEncoder(encoder)
        self.cond_proj = nn.Linear(encoder.dim, dim, bias=False)
        self.cell_emb = CoordEmbedding(dim)
        self.pos_proj = nn.Linear(3 + 6 * n_freqs, dim, bias=False)
        self.layers = nn.ModuleList([Block(dim, heads) for _ in range(depth)])
        self.norm = RMSNorm(dim)
        self.heads = heads
        self.log_slopes = None
        if distance_bias:
            # Slopes per unit-cube distance from 256 (a few cells) down to ~1 (global), per head.
            init = torch.tensor([math.log(256.0) * (1 - h / max(heads - 1, 1)) for h in range(heads)])
            self.log_slopes = nn.Parameter(init.repeat(depth, 1))

    def condition(self, points: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
        """(B, P, 3) points + normals -> (B, M, dim) prefix."""
        return self.cond_proj(self.encoder(points, normals))

    def forward(self, q: torch.Tensor, prefix: torch.Tensor, valid: torch.Tensor | None = None,
                mask: torch.Tensor | None = None, extra: torch.Tensor | None = None) -> torch.Tensor:
        """q (B, N, 3) long cells, prefix (B, M, dim) -> (B, N, dim) vertex features.

        ``extra`` (B, N, dim) is added to the vertex embeddings (e.g. local point features).
        """
        if valid is None:
            valid = torch.ones(q.shape[:2], dtype=torch.bool, device=q.device)
        x = self.cell_emb(q) + self.pos_proj(fourier_features(dequantize(q), self.n_freqs))
        if extra is not None:
            x = x + extra
        m = prefix.shape[1]
        x = torch.cat([prefix.to(x.dtype), x], dim=1)
        attn = full_attention_mask(valid, m, mask)
        if self.log_slopes is None:
            for layer in self.layers:
                x = layer(x, mask=attn)
            return self.norm(x[:, m:])
        # Additive float mask: -inf where not allowed, -slope * distance among vertices.
        dev = q.device
        dtype = torch.get_autocast_dtype(dev.type) if torch.is_autocast_enabled(dev.type) else x.dtype
        c = dequantize(q)
        dist = torch.cdist(c, c)  # (B, N, N)
        blocked = torch.zeros(attn.shape, dtype=dtype, device=dev).masked_fill(~attn, float("-inf"))
        for i, layer in enumerate(self.layers):
            bias = blocked.expand(-1, self.heads, -1, -1).clone()
            slope = self.log_slopes[i].exp().to(dist.dtype)
            bias[:, :, m:, m:] += (-slope[None, :, None, None] * dist[:, None]).to(dtype)
            x = layer(x, mask=bias)
        return self.norm(x[:, m:])
