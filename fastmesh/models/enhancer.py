"""The fidelity enhancer: 7-bit vertices (+ condition) -> continuous position inside each cell.

Quantisation and the 7-bit merge lose up to half a cell per axis; the enhancer looks at
all vertices and the condition (``backbone.VertexSetBackbone``) and predicts each
vertex's residual from its cell centre, in cell units, bounded to [-0.5, 0.5] by
``0.5 * tanh`` so a prediction never leaves its cell.  Trained with an L1 loss.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from ..tokenizer import dequantize
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
    encoder: EncoderConfig = field(default_factory=_small_encoder)


class Enhancer(nn.Module):
    def __init__(self, cfg: EnhancerConfig):
        super().__init__()
        self.cfg = cfg
        self.backbone = VertexSetBackbone(cfg.dim, cfg.depth, cfg.heads, cfg.encoder, cfg.n_freqs)
        self.head = nn.Linear(cfg.dim, 3)
        init_weights(self)

    @property
    def device(self) -> torch.device:
        return next(self.parameters()).device

    def forward(self, q: torch.Tensor, points: torch.Tensor, normals: torch.Tensor,
                valid: torch.Tensor | None = None) -> torch.Tensor:
        """q (B, N, 3) long, points/normals (B, P, 3), valid (B, N) bool -> (B, N, 3) residuals in cells."""
        prefix = self.backbone.condition(points, normals)
        h = self.backbone(q, prefix, valid)
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
        return dequantize(q) + res[0].double().cpu().numpy() / 128.0
