"""The generalized winding number of an oriented point cloud (Barill et al., "Fast winding numbers for soups and
clouds", 2018): each sample a dipole of the area it stands for; truncated for speed (:func:`winding_numbers`), and
read per Delaunay cell by the solid face stage (:func:`cell_winding`, ``fastmesh.faces.solid``)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

# Samples of the input the winding numbers sum over beyond NEAR_SPACINGS median point spacings of a query (all
# nearer): more cost time in proportion.
WINDING_POINTS = 2048
NEAR_SPACINGS = 6.0


def point_areas(points: np.ndarray, k: int = 8) -> np.ndarray:
    """(P,) the surface each of ``points`` (P, 3) stands for: a disc to its ``k``-th neighbour shared ``k`` ways."""
    dist = cKDTree(points).query(points, k=min(k + 1, len(points)))[0][:, -1]
    return np.pi * dist**2 / k


def winding_numbers(queries: np.ndarray, points: np.ndarray, normals: np.ndarray, seed: int = 0) -> np.ndarray:
    """The generalized winding number of oriented points at ``queries``, truncated for speed.

    Each point is a dipole of the area it stands for (:func:`point_areas`).  The points within
    ``NEAR_SPACINGS`` median spacings of a query count exactly; beyond, a random ``WINDING_POINTS`` of them stand
    for all (their areas scaled up to the total), which moves a far query's number by little and costs a
    fraction of the full sum.

    Parameters
    ----------
    queries : (Q, 3) float
    points, normals : (P, 3) float, normals unit and outward
    seed : int, of the far-field subset

    Returns
    -------
    (Q,) float, about 1 inside a closed surface and 0 outside
    """
    p = np.asarray(points, dtype=np.float64)
    n = np.asarray(normals, dtype=np.float64)
    q = np.asarray(queries, dtype=np.float64)
    area = point_areas(p)
    tree = cKDTree(p)
    spacing = float(np.median(tree.query(p, k=2)[0][:, 1]))
    near = NEAR_SPACINGS * spacing
    pairs = cKDTree(q).sparse_distance_matrix(tree, near, output_type="coo_matrix")
    d = p[pairs.col] - q[pairs.row]
    r = np.maximum(pairs.data, 1e-12)
    exact = np.bincount(pairs.row, area[pairs.col] * np.einsum("ki,ki->k", d, n[pairs.col]) / r**3, len(q))
    far = np.arange(len(p))
    if len(p) > WINDING_POINTS:
        far = np.random.default_rng(seed).choice(len(p), WINDING_POINTS, replace=False)
    fa = area[far] * (area.sum() / area[far].sum())
    # Centred on the query's box, as products of (B, 3) by (3, M): (p - q).n = p.n - q.n and
    # |p - q|^2 = |p|^2 - 2 p.q + |q|^2 without the (B, M, 3) differences (as ``closure._winding``).
    # In single precision, scaled to the points' box: the far field is a smooth sum of terms at least ``near``
    # away, and the cancellation in |p - q|^2 costs ~1e-7 of it.
    c = q.mean(0) if len(q) else np.zeros(3)
    unit = max(float(np.ptp(p, axis=0).max()), 1e-300)
    pf, nf, qc = ((p[far] - c) / unit).astype(np.float32), n[far].astype(np.float32), ((q - c) / unit)
    pn, pp = np.einsum("mi,mi->m", pf, nf), np.einsum("mi,mi->m", pf, pf)
    fa32, lim = (fa / unit**2).astype(np.float32), np.float32((near / unit) ** 2)
    out = np.empty(len(q))
    for s in range(0, len(q), 512):  # 512 x WINDING_POINTS pairs at a time: bounded memory
        b = qc[s:s + 512].astype(np.float32)
        r2 = pp[None] - 2.0 * (b @ pf.T) + np.einsum("bi,bi->b", b, b)[:, None]
        r2 = np.maximum(r2, lim)  # the near points count exactly, below
        w = (pn[None] - b @ nf.T) / (r2 * np.sqrt(r2))
        out[s:s + 512] = np.where(r2 > lim, w, 0.0) @ fa32
    return (out + exact) / (4 * np.pi)


def cell_winding(vertices: np.ndarray, tets: np.ndarray, points: np.ndarray, normals: np.ndarray,
                 seed: int = 0, known: dict | None = None) -> np.ndarray:
    """(K,) the input's generalized winding number in each cell (:func:`winding_numbers`): the mean at its
    centroid and the 4 points halfway from it to the corners.  A cell the input's surface crosses (the decoded
    vertices need not have the surface among their Delaunay triangles) reads the share of it inside; a sliver on
    the surface reads about the threshold, and the smoothness term labels it.  Each point's number is clipped to
    [-1, 1] first: a point next to a sample (a cell with a sample for a corner) reads that sample's dipole alone,
    without bound, and would outweigh the other four.

    ``known``: the numbers of cells read before (keyed by their corners, :func:`cell_keys`; a second cut with a few
    more vertices keeps most of its cells), filled with those read now.
    """
    corners = vertices[tets]  # (K, 4, 3)
    keys = cell_keys(corners) if known is not None else None
    out = np.array([known.get(k, np.nan) for k in keys]) if keys is not None else np.full(len(tets), np.nan)
    todo = np.flatnonzero(np.isnan(out))
    centre = corners[todo].mean(1)
    queries = np.concatenate([centre[:, None], 0.5 * (centre[:, None] + corners[todo])], axis=1).reshape(-1, 3)
    w = np.clip(winding_numbers(queries, points, normals, seed), -1.0, 1.0).reshape(len(todo), 5).mean(1)
    out[todo] = w
    if keys is not None:
        known.update(zip([keys[i] for i in todo], w.tolist(), strict=True))
    return out


def cell_keys(corners: np.ndarray) -> list[bytes]:
    """One key per cell of ``corners`` (K, 4, 3), the same whatever the order of its corners."""
    order = np.lexsort((corners[..., 2], corners[..., 1], corners[..., 0]), axis=-1)
    rows = np.ascontiguousarray(np.take_along_axis(corners, order[..., None], axis=1).reshape(len(corners), 12))
    return [r.tobytes() for r in rows]
