"""Data augmentation on continuous normalised meshes, before quantisation.

Augmenting before the 7-bit merge matters: a rotated mesh merges differently, and
the network must learn sequences of real quantised meshes, not rotated tokens.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..io import sample_triangles
from ..tokenizer import quantize_mesh


@dataclass
class AugmentConfig:
    rotate: bool = True  # random rotation about the up axis
    up_axis: int = 1  # y; corpus meshes are mixed y-up and z-up, so either is only a convention
    scale_min: float = 0.75  # anisotropic scale per axis in [scale_min, 1]
    jitter: float = 0.005  # std of Gaussian noise on condition points (unit cube)
    normal_jitter: float = 0.05


def augment_mesh(v: np.ndarray, cfg: AugmentConfig, rng: np.random.Generator) -> np.ndarray:
    """Rotate and scale (V, 3) normalised positions, then renormalise into the unit cube."""
    if cfg.rotate:
        a = rng.uniform(0, 2 * np.pi)
        c, s = np.cos(a), np.sin(a)
        i, j = [k for k in range(3) if k != cfg.up_axis]
        r = np.eye(3)
        r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
        v = v @ r.T
    if cfg.scale_min < 1:
        v = v * rng.uniform(cfg.scale_min, 1.0, size=3)
    lo, hi = v.min(0), v.max(0)
    return (v - (lo + hi) / 2) / max(float((hi - lo).max()), 1e-12)


def prepare_sample(v: np.ndarray, faces: np.ndarray, n_points: int, cfg: AugmentConfig | None,
                   rng: np.random.Generator):
    """Augment, quantise, and sample a condition point cloud from one mesh.

    Returns
    -------
    q : (V', 3) int64 cells; faces : (F', 3); cont : (V', 3) continuous positions;
    points, normals : (n_points, 3) float32 condition samples (jittered when augmenting).
    """
    if cfg is not None:
        v = augment_mesh(v, cfg, rng)
    q, f, cont = quantize_mesh(v, faces)
    pts, nrm = sample_triangles(v, faces, n_points, rng)
    if cfg is not None and cfg.jitter > 0:
        pts = pts + rng.normal(0, cfg.jitter, pts.shape).astype(np.float32)
        nrm = nrm + rng.normal(0, cfg.normal_jitter, nrm.shape).astype(np.float32)
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-8)
    return q, f, cont, pts, nrm


def grid_symmetry(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """One of the 48 symmetries of the cube: an axis permutation (3,) and per-axis signs (3,).

    They map the 7-bit grid onto itself (cell c <-> 127 - c), so the cell evidence of a mesh,
    computed once and stored (``fastmesh data cells``), moves with the mesh: the augmentation a
    decoder reading stored evidence can have, where a rotation by any angle would need new evidence.
    """
    return rng.permutation(3), rng.choice([-1.0, 1.0], size=3)


def apply_symmetry(v: np.ndarray, sym: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """(V, 3) positions in the unit cube centred at 0 -> the same under ``sym``."""
    perm, signs = sym
    return v[:, perm] * signs


def symmetric_cells(cells: np.ndarray, sym: tuple[np.ndarray, np.ndarray], levels: int) -> np.ndarray:
    """(C, 3) int cells -> their cells under ``sym`` (a sign of -1 maps cell c to levels - 1 - c)."""
    perm, signs = sym
    c = cells[:, perm]
    return np.where(signs < 0, levels - 1 - c, c)
