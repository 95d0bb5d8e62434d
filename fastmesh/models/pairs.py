"""Geometric pair evidence of the face model: what the input surface says about a vertex pair.

An artist's edge runs along the surface, is about as long as the local detail, and lies across
the surface normals at its ends; a pair that cuts through the inside of the shape or across a gap
is no edge, whatever the vertex features say.  The input shows this directly, so the edge head
reads it (the model should never have to learn what the input shows):

    stray_max, stray_mean : distance of the segment i-j from the input points, sampled at
                            ``samples`` points along it, in point spacings (clipped at STRAY_CLIP)
    log_length            : log(|x_j - x_i| / spacing)
    cos_hi, cos_lo        : the larger and the smaller of |n_i . e| and |n_j . e|, where e is the
                            unit segment and n the normal of the input point nearest the vertex

``spacing`` is the median nearest-neighbour distance of the input points, so the features do not
depend on the sample size or the shape's scale.  Distances are read, trilinearly, from an unsigned
distance grid over the unit cube (``grid`` nodes per axis), computed once per shape: no pair ever
meets the points directly, and the cost per pair is ``samples`` grid lookups.  Every feature is
exactly symmetric in (i, j), like the spacetime distances, so the logits stay symmetric.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

PAIR_FEATURES = 5
STRAY_CLIP = 8.0  # spacings; beyond this a segment is simply off the surface
NODE_CHUNK = 8192  # grid nodes x shapes measured against the points at once (bounds the distance matrix)


@dataclass
class PairContext:
    """Per-shape inputs of :func:`pair_features`.

    Attributes
    ----------
    xyz : (B, N, 3) float32 vertex positions (unit cube).
    normal : (B, N, 3) float32 unit normal of the input point nearest each vertex.
    grid : (B, 1, G, G, G) float32 distance to the input points in spacings; node (x, y, z) at
        ``grid[b, 0, z, y, x]`` (``grid_sample``'s layout), nodes spanning [-0.5, 0.5] per axis.
    spacing : (B,) float32 median nearest-neighbour distance of the input points.
    samples : int, points per segment.
    """

    xyz: torch.Tensor
    normal: torch.Tensor
    grid: torch.Tensor
    spacing: torch.Tensor
    samples: int

    def take(self, order: torch.Tensor) -> PairContext:
        """The same shapes with their vertices in ``order`` (N',) long."""
        return PairContext(self.xyz[:, order], self.normal[:, order], self.grid, self.spacing, self.samples)


def point_spacing(points: torch.Tensor) -> torch.Tensor:
    """(B, P, 3) points -> (B,) median distance of a point to its nearest neighbour."""
    d = torch.cdist(points, points)
    d.diagonal(dim1=1, dim2=2).fill_(float("inf"))
    return d.min(dim=2).values.median(dim=1).values.clamp(min=1e-6)


def distance_grid(points: torch.Tensor, size: int) -> torch.Tensor:
    """(B, P, 3) points -> (B, 1, size, size, size) distance of each grid node to the nearest point."""
    ax = torch.linspace(-0.5, 0.5, size, device=points.device)
    z, y, x = torch.meshgrid(ax, ax, ax, indexing="ij")
    nodes = torch.stack([x, y, z], dim=-1).reshape(-1, 3)  # row-major over (z, y, x)
    out = torch.empty(points.shape[0], nodes.shape[0], device=points.device)
    step = max(1, NODE_CHUNK // len(points))  # a training batch measures all its shapes at once
    for s in range(0, len(nodes), step):
        out[:, s:s + step] = torch.cdist(nodes[s:s + step].expand(len(points), -1, -1), points).min(dim=2).values
    return out.view(-1, 1, size, size, size)


def pair_context(xyz: torch.Tensor, points: torch.Tensor, normals: torch.Tensor, grid: int,
                 samples: int) -> PairContext:
    """:class:`PairContext` of vertices ``xyz`` (B, N, 3) on input ``points``/``normals`` (B, P, 3)."""
    with torch.no_grad(), torch.autocast(device_type=xyz.device.type, enabled=False):
        xyz, points, normals = xyz.float(), points.float(), normals.float()
        spacing = point_spacing(points)
        dist = distance_grid(points, grid) / spacing[:, None, None, None, None]
        nearest = torch.cdist(xyz, points).argmin(dim=2)  # (B, N)
        normal = F.normalize(torch.gather(normals, 1, nearest[..., None].expand(-1, -1, 3)), dim=-1)
    return PairContext(xyz, normal, dist, spacing, samples)


def pair_features(ctx: PairContext, start: int, stop: int, col_start: int = 0,
                  col_stop: int | None = None) -> torch.Tensor:
    """(B, r, c, PAIR_FEATURES) float32 features of the pairs (i, j), i in rows ``start:stop`` and j in
    columns ``col_start:col_stop`` (default: all)."""
    a = ctx.xyz[:, start:stop, None, :]  # (B, r, 1, 3)
    b = ctx.xyz[:, None, col_start:col_stop, :]  # (B, 1, c, 3)
    seg = b - a
    bsz, r, n, _ = seg.shape
    s = ctx.samples
    # Samples placed symmetrically about the midpoint, so (i, j) and (j, i) read the same points.
    t = (2 * torch.arange(s, device=seg.device, dtype=seg.dtype) + 1 - s) / (2 * s)  # t[S-1-k] == -t[k] exactly
    pts = ((a + b) / 2)[..., None, :] + t[:, None] * seg[..., None, :]  # (B, r, N, S, 3)
    d = F.grid_sample(ctx.grid, (2.0 * pts).view(bsz, r * n * s, 1, 1, 3), mode="bilinear",
                      padding_mode="border", align_corners=True).view(bsz, r, n, s)
    # Sum sample k with sample S-1-k first: the same sum, to the bit, for (i, j) and (j, i).
    half = (s + 1) // 2
    pair_sum = d[..., :half] + d.flip(-1)[..., :half]
    if s % 2:
        pair_sum[..., -1] = d[..., half - 1]
    stray_mean = pair_sum.sum(-1) / s
    length = seg.norm(dim=-1)
    unit = seg / length.clamp(min=1e-9)[..., None]
    ci = (ctx.normal[:, start:stop, None, :] * unit).sum(-1).abs()
    cj = (ctx.normal[:, None, col_start:col_stop, :] * unit).sum(-1).abs()
    log_length = torch.log((length / ctx.spacing[:, None, None]).clamp(min=0.05))
    return torch.stack([d.max(dim=-1).values.clamp(max=STRAY_CLIP), stray_mean.clamp(max=STRAY_CLIP),
                        log_length, torch.maximum(ci, cj), torch.minimum(ci, cj)], dim=-1)
