"""Stage II: the face model (vertices + condition -> adjacency logits in one pass).

A bidirectional transformer embeds the vertices (``backbone.VertexSetBackbone``); the
multi-head spacetime edge head of METHOD.md scores every pair:

    u = proj(h_i) split per head h into halves (u1, u2), each L2-normalised (3 dims)
    d_h(i, j) = ||u1_i - u1_j||^2 - ||u2_i - u2_j||^2 = 2 (u2_i . u2_j - u1_i . u1_j)
    logit(i, j) = MLP_{H (+5) -> hidden -> 1}(d_1 .. d_H [, pair evidence])

With unit halves d is a difference of dot products, so each head is one batched matmul;
the result is symmetric by construction.  The N x N x H tensor is built ``pair_chunk``
rows at a time, which bounds memory at N = 4000 (``benchmarks/face_memory.py``).  With
``pair_evidence`` the MLP also reads what the input surface says about each pair
(``models.pairs``: how far the segment strays from the surface, its length in point spacings,
the input normals at its ends against it); those weights start at zero, so a model trained
without them continues exactly where it was.

Trained with the asymmetric loss (Ridnik et al.: gamma+ = 0, gamma- = 3, clip 0.05) over
pairs i < j, under random attention masks like those of prediction filtering (so the
masked passes at inference are in distribution; ``training.tasks.FaceTask``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ..faces.filtering import FilterConfig, predict_edges
from ..tokenizer.grid import dequantize
from .backbone import VertexSetBackbone
from .encoder import EncoderConfig
from .layers import init_weights
from .pairs import PAIR_FEATURES, PairContext, pair_context, pair_features

OUTSIDE = -1.0e4  # the logit given to a pair outside the columns asked for: no edge


@dataclass
class FaceModelConfig:
    dim: int = 256
    depth: int = 6
    heads: int = 8
    edge_heads: int = 32
    edge_head_dim: int = 6  # two L2-normalised halves of 3
    edge_mlp_hidden: int = 16
    pair_chunk: int = 256  # rows of the pair tensor computed at once
    n_freqs: int = 6  # Fourier features of the cell centre
    # Geometric attention bias among vertices (models.backbone).  Off by default: in our first
    # comparison (same batches, 200 steps) it trained no faster and cost ~1.3x per step.
    distance_bias: bool = False
    pair_evidence: bool = False  # geometric pair features in the edge MLP (models.pairs)
    pair_grid: int = 32  # nodes per axis of the distance grid the pair features read
    pair_samples: int = 6  # points sampled along each segment
    encoder: EncoderConfig = field(default_factory=EncoderConfig)


def asymmetric_loss(logits: torch.Tensor, target: torch.Tensor, weight: torch.Tensor | None = None,
                    gamma_pos: float = 0.0, gamma_neg: float = 3.0, clip: float = 0.05) -> torch.Tensor:
    """Summed asymmetric loss (Ridnik et al. 2021) of binary ``logits`` against ``target``.

    Positives: -(1 - p)^gamma_pos log p.  Negatives: with the shifted probability
    p_m = max(p - clip, 0), -p_m^gamma_neg log(1 - p_m).  Easy negatives (p < clip) cost
    nothing and the rest are down-weighted, which suits the very unbalanced pair labels.

    Parameters
    ----------
    logits : (…) float
    target : (…) bool
    weight : (…) bool or float, optional; pairs with weight 0 are ignored.

    Returns
    -------
    scalar: the sum over weighted elements (callers normalise, e.g. by the positive count).
    """
    x = logits.float()
    p = torch.sigmoid(x)
    pos = F.logsigmoid(x)
    if gamma_pos:
        pos = pos * (1 - p).pow(gamma_pos)
    p_m = (p - clip).clamp(min=0) if clip > 0 else p
    # 1 - p_m >= clip > 0, so the log is finite; without clip use log(1 - p) = logsigmoid(-x).
    neg = torch.log1p(-p_m) if clip > 0 else F.logsigmoid(-x)
    neg = neg * p_m.pow(gamma_neg)
    loss = -torch.where(target.bool(), pos, neg)
    if weight is not None:
        loss = loss * weight.to(loss.dtype)
    return loss.sum()


class FaceModel(nn.Module):
    def __init__(self, cfg: FaceModelConfig):
        super().__init__()
        if cfg.edge_head_dim % 2:
            raise ValueError("edge_head_dim must be even (two halves)")
        self.cfg = cfg
        self.backbone = VertexSetBackbone(cfg.dim, cfg.depth, cfg.heads, cfg.encoder, cfg.n_freqs,
                                          cfg.distance_bias)
        self.edge_proj = nn.Linear(cfg.dim, cfg.edge_heads * cfg.edge_head_dim)
        self.edge_fc = nn.Linear(cfg.edge_heads, cfg.edge_mlp_hidden)
        self.edge_out = nn.Linear(cfg.edge_mlp_hidden, 1)
        self.pair_fc = nn.Linear(PAIR_FEATURES, cfg.edge_mlp_hidden, bias=False) if cfg.pair_evidence else None
        init_weights(self)
        # Unit halves make d lie in [-4, 4] per head: give the MLP unit-scale weights, and start
        # from "no edge" (p ~ 0.05, where the clipped negative loss vanishes): edges are rare.
        nn.init.normal_(self.edge_fc.weight, std=cfg.edge_heads ** -0.5)
        nn.init.normal_(self.edge_out.weight, std=cfg.edge_mlp_hidden ** -0.5)
        nn.init.constant_(self.edge_out.bias, -3.0)
        if self.pair_fc is not None:
            nn.init.zeros_(self.pair_fc.weight)

    @property
    def device(self) -> torch.device:
        return next(self.parameters()).device

    # ------------------------------------------------------------------ pieces

    def edge_factors(self, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, N, dim) features -> left/right factors (B, H, N, hd) with d = 2 * left @ right^T."""
        b, n, _ = h.shape
        c = self.cfg.edge_head_dim // 2
        u = self.edge_proj(h).float().view(b, n, self.cfg.edge_heads, 2, c)
        u = F.normalize(u, dim=-1).permute(0, 2, 1, 3, 4)  # (B, H, N, 2, c)
        u1, u2 = u[..., 0, :], u[..., 1, :]
        return torch.cat([u2, -u1], dim=-1), torch.cat([u2, u1], dim=-1)

    def pair_context(self, q: torch.Tensor, points: torch.Tensor | None,
                     normals: torch.Tensor | None) -> PairContext | None:
        """What the pair features of vertices ``q`` (B, N, 3) long need from the input (None without them)."""
        if not self.cfg.pair_evidence:
            return None
        if points is None or normals is None:
            raise ValueError("this face model reads pair evidence: it needs the input points and normals")
        return pair_context(dequantize(q), points, normals, self.cfg.pair_grid, self.cfg.pair_samples)

    def edge_logits(self, h: torch.Tensor, chunk: int | None = None, pairs: PairContext | None = None,
                    columns: np.ndarray | None = None) -> torch.Tensor:
        """(B, N, dim) vertex features -> (B, N, N) float32 edge logits, ``chunk`` rows at a time.

        ``pairs`` (from :meth:`pair_context`, vertices in the order of ``h``) is required when the
        model reads pair evidence.

        ``columns`` (N, 2) int: the inference path.  Row i needs only the logits of columns
        ``columns[i, 0] <= j < columns[i, 1]``, the spans of a symmetric mask (:func:`mask_spans`; all
        columns: ``[[0, N]] * N``).  The logits are symmetric in (i, j) (spacetime distances and pair
        features both are), so each row chunk computes the columns its rows need from the diagonal on
        and the lower triangle is their mirror image: half the work of a whole pass, and under a
        filtering mask only its band.  Pairs no row asks for get ``OUTSIDE``.  Equal to the whole
        computation up to the rounding of matrix products, and exactly symmetric.
        """
        if (pairs is None) != (self.pair_fc is None):
            raise ValueError("pair evidence: give a PairContext exactly when the model reads it")
        left, right = self.edge_factors(h)
        b, heads, n, hd = left.shape
        chunk = chunk or self.cfg.pair_chunk
        w1, b1 = self.edge_fc.weight.float(), self.edge_fc.bias.float()
        w2, b2 = self.edge_out.weight.float()[0], self.edge_out.bias.float()
        k = w1.shape[0]
        # The first layer of the MLP is linear in the H distances d_h = 2 left_h . right_h, so it folds into
        # the left factor: pre_k(i, j) = sum_(h,c) (2 w1[k, h] left_h(i)_c) right_h(j)_c, one matrix product
        # with a contraction of H * hd instead of H small ones and an (H, rows, N) intermediate.
        folded = (2.0 * w1[None, :, :, None, None] * left[:, None]).permute(0, 1, 3, 2, 4).reshape(b, k, n, heads * hd)
        flat_right = right.permute(0, 2, 1, 3).reshape(b, n, heads * hd).transpose(1, 2)[:, None]  # (B, 1, H*hd, N)
        out = left.new_full((b, n, n), OUTSIDE) if columns is not None else None
        rows = []
        # float32 on purpose, outside autocast: these contractions are tiny (6, 32 and 16 wide) and
        # memory-bound, and under bf16 autocast oneDNN's AMX matmul dies on some of their shapes
        # (SIGFPE in its blocking heuristic, seen on Sapphire-Rapids-class CPUs with torch 2.13).
        with torch.autocast(device_type=h.device.type, enabled=False):
            for s in range(0, n, chunk):
                r = min(chunk, n - s)
                c0, c1 = 0, n
                if columns is not None:
                    c0, c1 = max(s, int(columns[s:s + r, 0].min())), int(columns[s:s + r, 1].max())
                    if c1 <= c0:
                        continue
                w = c1 - c0
                pre = (folded[:, :, s:s + r] @ flat_right[..., c0:c1]).reshape(b, k, r * w) + b1[:, None]
                if pairs is not None:
                    f = pair_features(pairs, s, s + r, c0, c1).reshape(b, r * w, PAIR_FEATURES)
                    pre = pre + torch.einsum("kf,bxf->bkx", self.pair_fc.weight.float(), f)
                hid = F.gelu(pre)
                logit = (torch.einsum("k,bkx->bx", w2, hid) + b2).view(b, r, w)
                if out is None:
                    rows.append(logit)
                    continue
                if c0 == s:  # the chunk's own square: its upper triangle, mirrored
                    sq = min(r, w)
                    upper = torch.triu(logit[:, :, :sq])
                    logit[:, :sq, :sq] = upper + torch.triu(upper, 1).transpose(1, 2)
                out[:, s:s + r, c0:c1] = logit
                out[:, c0:c1, s:s + r] = logit.transpose(1, 2)
        return torch.cat(rows, dim=1) if out is None else out

    # ------------------------------------------------------------------ training

    def forward(self, q: torch.Tensor, points: torch.Tensor | None = None, normals: torch.Tensor | None = None,
                valid: torch.Tensor | None = None, mask: torch.Tensor | None = None,
                prefix: torch.Tensor | None = None) -> torch.Tensor:
        """Edge logits (B, N, N) of vertices ``q`` (B, N, 3) long.

        The condition is ``prefix`` (B, M, dim) or computed from ``points``/``normals`` (B, P, 3).
        ``valid`` (B, N) bool marks real vertices (padding is never attended); ``mask``
        (B, N, N) bool restricts which vertices each vertex attends to (True = may attend;
        the prefix is always visible).
        """
        if prefix is None:
            prefix = self.backbone.condition(points, normals)
        return self.edge_logits(self.backbone(q, prefix, valid, mask), pairs=self.pair_context(q, points, normals))

    # ------------------------------------------------------------------ inference

    def predictor(self, q: np.ndarray, points: np.ndarray, normals: np.ndarray):
        """A ``filtering.Predictor`` for one shape: ``predict(order, mask) -> (N, N) logits``.

        The condition is encoded once; each call permutes the vertices by ``order``, uses
        ``mask`` (N, N) bool in that order as the attention mask among vertices, and
        returns float32 logits in that order.
        """
        dev = self.device
        qt = torch.as_tensor(np.asarray(q), dtype=torch.long, device=dev)[None]
        pts, nrm = _f32(points, dev)[None], _f32(normals, dev)[None]
        with torch.no_grad():
            prefix = self.backbone.condition(pts, nrm)
            pairs = self.pair_context(qt, pts, nrm)

        def predict(order: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
            with torch.no_grad():
                idx = torch.as_tensor(np.asarray(order), dtype=torch.long, device=dev)
                mask = None if mask is None else np.asarray(mask, dtype=bool)
                m = None if mask is None else torch.as_tensor(mask, device=dev)[None]
                h = self.backbone(qt[:, idx], prefix, mask=m)
                # The edge head is most of a pass's cost: it computes one triangle of the symmetric logits,
                # and under a mask (filtering, which reads a pair only where both of its rows allow it)
                # only the band the mask allows.
                n = len(idx)
                cols = np.tile([0, n], (n, 1)) if mask is None else mask_spans(mask & mask.T)
                return self.edge_logits(h, pairs=None if pairs is None else pairs.take(idx),
                                        columns=cols)[0].cpu().numpy()

        return predict

    def predict_edges(self, q: np.ndarray, points: np.ndarray, normals: np.ndarray,
                      filtering: FilterConfig | None = None, return_logits: bool = False):
        """(E, 2) int64 predicted edges (i < j) among vertices ``q`` (N, 3).

        Without ``filtering``: one unmasked pass, edges where the symmetrised probability
        exceeds 0.5.  With it: ``filtering.filter_predictions`` (re-predictions under masks); see
        ``filtering.predict_edges``.
        With ``return_logits``: ``(edges, logits)``, the (N, N) float32 logits of the unmasked pass.
        """
        n = len(q)
        if n < 2:
            edges = np.zeros((0, 2), dtype=np.int64)
            return (edges, np.zeros((n, n), dtype=np.float32)) if return_logits else edges
        edges, logits = predict_edges(self.predictor(q, points, normals), n, filtering or FilterConfig(),
                                      filtering is not None)
        return (edges, logits) if return_logits else edges


def mask_spans(mask: np.ndarray) -> np.ndarray:
    """(N, N) bool -> (N, 2) int64: per row the first allowed column and one past the last (0, 0: none)."""
    any_ = mask.any(1)
    first = np.where(any_, mask.argmax(1), 0)
    last = np.where(any_, mask.shape[1] - mask[:, ::-1].argmax(1), 0)
    return np.stack([first, last], 1).astype(np.int64)


def _f32(a, device) -> torch.Tensor:
    return torch.as_tensor(np.asarray(a, dtype=np.float32), device=device)
