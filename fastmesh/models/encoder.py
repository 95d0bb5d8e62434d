"""Point encoder: a point cloud with normals -> a fixed set of latent tokens.

Perceiver-style: Fourier features of each point (plus its normal) are read by a
set of learned latent queries through one cross-attention, then refined by a few
self-attention layers.  Cost is linear in the number of points, and the output
(``n_latents`` x ``dim``) conditions every FastMesh network as a prefix.

With ``anchors`` > 0 the queries are not learned vectors but the features of that many
farthest-point samples of the input: each output token then belongs to a place on the
surface, and the vertex decoder adds the cell embedding of that place to it, so
"which input region is near the next vertex" becomes a similarity between embeddings
the decoder already uses for its own vertices (see ``VertexDecoder.condition``).
With learned latents (``anchors`` = 0) a decoder still ignores its condition after three
epochs (``configs/vertex-latents.json``: it emits one sequence for every shape).

Why a prefix rather than cross-attention in the decoder: with a KV cache the prefix
is prefilled once per shape and each decoded token attends to ``n_latents`` more
keys (64 by default: cheap next to the sequence); cross-attention would add a second
attention and a second cache to every layer for no measured gain at this size.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from .layers import Block, RMSNorm, fourier_features


@dataclass
class EncoderConfig:
    n_points: int = 2048  # samples of the input surface (the authors used 8192 on GPUs)
    n_latents: int = 64
    dim: int = 256
    depth: int = 2  # self-attention layers after the cross-attention
    heads: int = 4
    n_freqs: int = 8
    anchors: int = 0  # > 0: farthest-point-sampled anchor queries replace the n_latents learned ones


def farthest_point_sample(points: torch.Tensor, m: int) -> torch.Tensor:
    """Indices (B, m) of ``m`` farthest-point samples of (B, P, 3) points, starting at point 0.

    Deterministic given the points; m sequential steps of O(B * P) work (about 10 ms for
    B = 16, P = 2048, m = 256 on a laptop core), so it runs inside the forward pass.
    """
    b, p, _ = points.shape
    m = min(m, p)
    rows = torch.arange(b, device=points.device)
    idx = torch.zeros(b, m, dtype=torch.long, device=points.device)
    dist = torch.full((b, p), float("inf"), device=points.device, dtype=points.dtype)
    far = torch.zeros(b, dtype=torch.long, device=points.device)
    for i in range(m):
        idx[:, i] = far
        dist = torch.minimum(dist, (points - points[rows, far][:, None]).square().sum(-1))
        far = dist.argmax(-1)
    return idx


class PointEncoder(nn.Module):
    def __init__(self, cfg: EncoderConfig):
        super().__init__()
        self.cfg = cfg
        in_dim = 3 + 6 * cfg.n_freqs + 3
        self.point_proj = nn.Sequential(nn.Linear(in_dim, cfg.dim), nn.GELU(), nn.Linear(cfg.dim, cfg.dim))
        if not cfg.anchors:
            self.latents = nn.Parameter(torch.randn(cfg.n_latents, cfg.dim) * 0.02)
        self.read = Block(cfg.dim, cfg.heads, cross_dim=cfg.dim)
        self.layers = nn.ModuleList([Block(cfg.dim, cfg.heads) for _ in range(cfg.depth)])
        self.norm = RMSNorm(cfg.dim)

    @property
    def n_tokens(self) -> int:
        return self.cfg.anchors or self.cfg.n_latents

    def forward(self, points: torch.Tensor, normals: torch.Tensor, return_anchors: bool = False):
        """points, normals: (B, P, 3) in the unit cube -> latents (B, n_tokens, dim).

        With ``return_anchors`` also the (B, anchors, 3) anchor positions (None without anchors).
        """
        feats = self.point_proj(torch.cat([fourier_features(points, self.cfg.n_freqs), normals], dim=-1))
        anchor_pts = None
        if self.cfg.anchors:
            with torch.no_grad():
                idx = farthest_point_sample(points.float(), self.cfg.anchors)
            x = feats.gather(1, idx[..., None].expand(-1, -1, feats.shape[-1]))
            anchor_pts = points.gather(1, idx[..., None].expand(-1, -1, 3))
        else:
            x = self.latents.expand(points.shape[0], -1, -1)
        x = self.read(x, context=feats)
        for layer in self.layers:
            x = layer(x)
        x = self.norm(x)
        return (x, anchor_pts) if return_anchors else x
