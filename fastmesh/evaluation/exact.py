"""Distances to the exact surface: samples of each shape measured to the other's triangles (closest point),
so that a result equal to its input reads about 0 instead of the sample-to-sample floor.

    CD = 100 * (mean_a d(a, B) + mean_b d(b, A)) / 2,   HD = 100 * max(max_a d(a, B), max_b d(b, A))

with ``a`` dense samples of A and ``d(a, B)`` the distance to B's nearest triangle, in % of the longest side of
the frame's box.  A point cloud has no triangles: its samples are its points, and a sample of the other
shape is measured to the nearest of the discs the points stand for (:func:`distance_to_cloud`).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..faces.meshops import point_triangle_distance
from ..shapes.io import sample_triangles
from ..shapes.shape import Normalization
from .metrics import N_SAMPLES, SEED, SurfaceDistance

DISC_NEIGHBOURS = 6  # a cloud's point stands for a disc out to its 6th nearest neighbour: no gaps between discs
# Discs tried per sample: near a crease the nearest points can all lie on the other side's discs.
DISC_CANDIDATES = 16


def distance_to_mesh(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Exact distance from each point to the nearest triangle of a mesh.

    The triangle with the nearest centroid gives an upper bound ``u``;
    then only triangles whose centroid lies within ``u`` plus their own radius are measured.  Triangles are
    grouped by radius (powers of two) so that a few large faces do not widen every query.

    Parameters
    ----------
    points : (N, 3) float
    vertices : (V, 3) float
    faces : (F, 3) int, F >= 1

    Returns
    -------
    (N,) float64
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces, dtype=np.int64).reshape(-1, 3)]
    if len(tri) == 0:
        raise ValueError("distance_to_mesh needs at least one face")
    centre = tri.mean(1)
    best = point_triangle_distance(p, tri[cKDTree(centre).query(p)[1]])
    radius = np.linalg.norm(tri - centre[:, None], axis=2).max(1)
    top = max(float(radius.max()), 1e-300)
    level = np.clip(np.floor(np.log2(np.maximum(radius, 1e-300) / top)), -16, 0)
    for k in np.unique(level):
        group = np.flatnonzero(level == k)
        hits = cKDTree(centre[group]).query_ball_point(p, best + float(radius[group].max()), return_sorted=False)
        sizes = np.fromiter((len(h) for h in hits), dtype=np.int64, count=len(p))
        if not sizes.sum():
            continue
        pi = np.repeat(np.arange(len(p)), sizes)
        fi = group[np.concatenate([np.asarray(h, dtype=np.int64) for h in hits if len(h)])]
        np.minimum.at(best, pi, point_triangle_distance(p[pi], tri[fi]))
    return best


def distance_to_cloud(points: np.ndarray, cloud: np.ndarray, normals: np.ndarray | None = None) -> np.ndarray:
    """Distance from each point to the nearest of a cloud's discs: each cloud point stands for a disc about
    its normal (a ball without normals) of radius the distance to its ``DISC_NEIGHBOURS``-th neighbour.

    Parameters
    ----------
    points : (N, 3) float
    cloud : (M, 3) float, M >= 2
    normals : (M, 3) float, optional

    Returns
    -------
    (N,) float64
    """
    c = np.asarray(cloud, dtype=np.float64).reshape(-1, 3)
    tree = cKDTree(c)
    k = min(DISC_NEIGHBOURS, len(c) - 1)
    reach = tree.query(c, k=k + 1)[0][:, -1] if k > 0 else np.zeros(len(c))
    dist, idx = tree.query(np.asarray(points, dtype=np.float64).reshape(-1, 3), k=min(DISC_CANDIDATES, len(c)))
    dist, idx = dist.reshape(len(dist), -1), idx.reshape(len(idx), -1)
    offset = np.asarray(points, dtype=np.float64).reshape(-1, 1, 3) - c[idx]
    if normals is None:
        out = np.maximum(dist - reach[idx], 0.0)
    else:
        n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)[idx]
        n = n / np.maximum(np.linalg.norm(n, axis=2, keepdims=True), 1e-300)
        across = np.einsum("nkd,nkd->nk", offset, n)
        along = np.sqrt(np.maximum(dist ** 2 - across ** 2, 0.0))
        out = np.hypot(across, np.maximum(along - reach[idx], 0.0))
    return out.min(1)


def exact_distance(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray | None],
                   frame: Normalization, n: int = N_SAMPLES, seed: int = SEED,
                   b_normals: np.ndarray | None = None) -> SurfaceDistance:
    """CD and HD between mesh ``a`` = (vertices, faces) and ``b`` (a mesh, or a point cloud with faces None),
    both in ``frame`` (``Normalization``: longest side 1), from ``n`` samples of each to the other's surface.

    Parameters
    ----------
    a : (V, 3) float, (F, 3) int, F >= 1
    b : (W, 3) float, (G, 3) int or None
    frame : Normalization
    n : int, samples drawn on each mesh (a cloud gives at most ``n`` of its points, evenly picked)
    seed : int
    b_normals : (W, 3) float, optional, a cloud's normals (its discs then lie flat)
    """
    rng = np.random.default_rng(seed)
    va = frame.apply(np.asarray(a[0], dtype=np.float64))
    fa = np.asarray(a[1], dtype=np.int64).reshape(-1, 3)
    vb = frame.apply(np.asarray(b[0], dtype=np.float64))
    sa = sample_triangles(va, fa, n, rng)[0].astype(np.float64)
    if b[1] is None or len(b[1]) == 0:
        sb = vb if len(vb) <= n else vb[np.linspace(0, len(vb) - 1, n).astype(np.int64)]
        d_ab = distance_to_cloud(sa, vb, b_normals)
    else:
        fb = np.asarray(b[1], dtype=np.int64).reshape(-1, 3)
        sb = sample_triangles(vb, fb, n, rng)[0].astype(np.float64)
        d_ab = distance_to_mesh(sa, vb, fb)
    d_ba = distance_to_mesh(sb, va, fa)
    return SurfaceDistance(cd=float(100.0 * (d_ab.mean() + d_ba.mean()) / 2),
                           hd=float(100.0 * max(d_ab.max(), d_ba.max())),
                           mean_ab=float(100.0 * d_ab.mean()), mean_ba=float(100.0 * d_ba.mean()))
