"""Data augmentation on continuous normalised meshes, before quantisation.

Augmenting before the 7-bit merge matters: a rotated mesh merges differently, and
the network must learn sequences of real quantised meshes, not rotated tokens.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..faces.meshops import face_sides
from ..shapes.io import sample_triangles
from ..tokenizer import dequantize, quantize_mesh
from ..tokenizer.grid import LEVELS


@dataclass
class AugmentConfig:
    rotate: bool = True  # random rotation about the up axis
    up_axis: int = 1  # y; corpus meshes are mixed y-up and z-up, so either is only a convention
    scale_min: float = 0.75  # anisotropic scale per axis in [scale_min, 1]
    jitter: float = 0.005  # std of Gaussian noise on condition points (unit cube)
    normal_jitter: float = 0.05
    # Vertex sets like a decoder's, for the face model (``perturb_vertex_set``): the share of samples
    # perturbed, and the rates inside one; 0 = always the artist's own vertices.
    perturb: float = 0.0
    vertex_jitter: float = 0.0  # share of vertices moved by one cell along one axis
    vertex_drop: float = 0.0  # share of vertices dropped (collapsed into a neighbour)
    vertex_extra: float = 0.0  # extra vertices on the surface, per vertex (faces split)


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


def perturb_vertex_set(q: np.ndarray, faces: np.ndarray, cfg: AugmentConfig,
                       rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A vertex set a decoder might emit for this mesh, with the faces an artist would give it.

    Some vertices are dropped, each collapsed into an adjacent kept vertex (the faces follow it,
    those that degenerate go); some faces are split at a point inside them (an extra vertex on the
    surface, three faces); some vertices move by one cell.  The result is canonical again
    (``quantize_mesh``: merged cells, clean faces, sorted), as the decoder's vertices are.

    Parameters
    ----------
    q : (V, 3) int cells; faces : (F, 3) int.

    Returns
    -------
    q : (V', 3) int64; faces : (F', 3) int64.
    """
    q = np.asarray(q, dtype=np.int64)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    n = len(q)
    if cfg.vertex_drop > 0 and len(f):
        drop = rng.random(n) < cfg.vertex_drop
        e = face_sides(f)
        e = np.concatenate([e, e[:, ::-1]])
        e = e[drop[e[:, 0]] & ~drop[e[:, 1]]]
        e = e[rng.permutation(len(e))]
        into = np.arange(n)
        first = np.unique(e[:, 0], return_index=True)[1]  # one random kept neighbour per dropped vertex
        into[e[first, 0]] = e[first, 1]
        f = into[f]
    if cfg.vertex_extra > 0 and len(f):
        k = min(len(f), rng.binomial(n, cfg.vertex_extra))
        split = rng.choice(len(f), size=k, replace=False)
        w = rng.dirichlet(np.ones(3), size=k)
        new = np.rint(np.einsum("kc,kcd->kd", w, q[f[split]])).astype(np.int64)
        idx = len(q) + np.arange(k)
        q = np.concatenate([q, new])
        a, b, c = f[split].T
        f = np.concatenate([np.delete(f, split, axis=0),
                            np.stack([a, b, idx], 1), np.stack([b, c, idx], 1), np.stack([c, a, idx], 1)])
    if cfg.vertex_jitter > 0:
        q = q.copy()
        moved = np.flatnonzero(rng.random(len(q)) < cfg.vertex_jitter)
        q[moved, rng.integers(0, 3, len(moved))] += rng.choice([-1, 1], len(moved))
        q = np.clip(q, 0, LEVELS - 1)
    q, f, _ = quantize_mesh(dequantize(q), f)
    return q, f
