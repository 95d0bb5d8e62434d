"""The fidelity enhancer: 7-bit vertices (+ condition) -> continuous position inside each cell.

Quantisation and the 7-bit merge lose up to half a cell per axis; the enhancer looks at
all vertices and the condition (``backbone.VertexSetBackbone``) and predicts each
vertex's residual from its cell centre, in cell units, bounded to [-0.5, 0.5] by
``0.5 * tanh`` so a prediction never leaves its cell.  Trained with an L1 loss.

The global latents cannot place a surface to a fraction of a cell (1/128 of the cube),
so each vertex also sees its ``local_k`` nearest condition points, as offsets from its
cell centre in cell units (plus their normals), pooled by a small PointNet: where the
surface passes through and near the cell is what decides the residual.  The denser the
condition points, the better; train and infer with similar densities.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from ..tokenizer.grid import LEVELS, dequantize
from .backbone import VertexSetBackbone
from .encoder import EncoderConfig
from .layers import init_weights


def _small_encoder() -> EncoderConfig:
    return EncoderConfig(n_latents=32, dim=192, depth=1, heads=4)


@dataclass
class EnhancerConfig:
    dim: int = 192
    depth: int = 4
    heads: int = 6
    n_freqs: int = 6
    local_k: int = 16  # nearest condition points per vertex (0 = no local features)
    local_range: float = 16.0  # cells: offsets are scaled by this and clipped to [-1, 1]
    local_dim: int = 96  # width of the local PointNet (run on N * k points: keep it narrow)
    encoder: EncoderConfig = field(default_factory=_small_encoder)


class LocalPoints(nn.Module):
    """PointNet over the k nearest condition points of each cell centre (offsets in cells)."""

    def __init__(self, dim: int, k: int, local_range: float, width: int):
        super().__init__()
        self.k, self.range = k, local_range
        self.mlp = nn.Sequential(nn.Linear(11, width), nn.GELU(), nn.Linear(width, width))
        self.out = nn.Linear(width, dim, bias=False)

    def forward(self, centres: torch.Tensor, points: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
        """centres (B, N, 3), points/normals (B, P, 3) -> (B, N, dim)."""
        b, n, _ = centres.shape
        k = min(self.k, points.shape[1])
        dist, idx = torch.cdist(centres.float(), points.float()).topk(k, dim=-1, largest=False)
        g = idx.reshape(b, n * k, 1).expand(-1, -1, 3)
        nb = torch.gather(points, 1, g).view(b, n, k, 3)
        nrm = torch.gather(normals, 1, g).view(b, n, k, 3)
        scale = LEVELS / self.range
        off = nb - centres[:, :, None]
        # Tangent-plane offset of each neighbour: the displacement that puts the cell centre on
        # that point's plane.  Explicit because an MLP approximates this bilinear form poorly.
        plane = (off * nrm).sum(-1, keepdim=True)
        feats = torch.cat([(off * scale).clamp(-1, 1), nrm, (dist * scale).clamp(max=1)[..., None],
                           (plane * LEVELS).clamp(-2, 2), (plane * nrm * LEVELS).clamp(-2, 2)], dim=-1)  # cells
        feats = self.mlp(feats)
        return self.out(feats.max(dim=2).values)


class Enhancer(nn.Module):
    def __init__(self, cfg: EnhancerConfig):
        super().__init__()
        self.cfg = cfg
        self.backbone = VertexSetBackbone(cfg.dim, cfg.depth, cfg.heads, cfg.encoder, cfg.n_freqs)
        self.local = LocalPoints(cfg.dim, cfg.local_k, cfg.local_range, cfg.local_dim) if cfg.local_k > 0 else None
        self.head = nn.Linear(cfg.dim, 3)
        init_weights(self)

    @property
    def device(self) -> torch.device:
        return next(self.parameters()).device

    def forward(self, q: torch.Tensor, points: torch.Tensor, normals: torch.Tensor,
                valid: torch.Tensor | None = None) -> torch.Tensor:
        """q (B, N, 3) long, points/normals (B, P, 3), valid (B, N) bool -> (B, N, 3) residuals in cells."""
        prefix = self.backbone.condition(points, normals)
        extra = None if self.local is None else self.local(dequantize(q), points, normals)
        h = self.backbone(q, prefix, valid, extra=extra)
        return 0.5 * torch.tanh(self.head(h).float())

    @staticmethod
    def l1(pred: torch.Tensor, target: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        """Mean absolute error (cells) over valid vertices and axes."""
        w = valid[..., None].to(pred.dtype)
        return ((pred - target).abs() * w).sum() / (3 * w.sum()).clamp(min=1)

    def refine(self, q: np.ndarray, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """(N, 3) int cells -> (N, 3) float64 normalised positions: cell centre + residual / 128."""
        q = np.asarray(q, dtype=np.int64)
        if len(q) == 0:
            return np.zeros((0, 3))
        dev = self.device
        with torch.no_grad():
            res = self(torch.as_tensor(q, device=dev)[None],
                       torch.as_tensor(np.asarray(points, dtype=np.float32), device=dev)[None],
                       torch.as_tensor(np.asarray(normals, dtype=np.float32), device=dev)[None])
        return dequantize(q) + res[0].double().cpu().numpy() / LEVELS
