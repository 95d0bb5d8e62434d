"""The noise of a scan, read from its points: how far they lie off the planes of their neighbours where the
surface itself is flat at that scale (``planar`` holds a scan's planes at its own noise, and keeps those as flat
as it: :func:`flat_only`)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

# The noise is read from the planes of the NOISE_NEAR and NOISE_FAR nearest neighbours of NOISE_PROBES points;
# curvature, not noise, where the far planes' RMS exceeds CURVED_GROWTH times the near ones' (a noisy box: 1.2; a
# smooth sphere or cylinder sampled as densely: 4 to 6).
NOISE_NEAR = 12
NOISE_FAR = 48
NOISE_PROBES = 1024  # the median over this many varies by about 2 %
CURVED_GROWTH = 1.6
SIDE_COS = 0.5  # neighbours whose normals turn by more than 60 degrees lie on another side (``noise_level``)
# A scan's plane lies off its points by at most this many noise levels in RMS (:func:`flat_only`; a flat side: 1.0
# to 1.25; a facet over a noisy cylinder: 1.7 or more).
FLAT_RMS = 1.4


def noise_level(points: np.ndarray, normals: np.ndarray | None = None) -> float:
    """The standard deviation of the points' noise off their surface, or 0 where the surface's own curvature,
    not noise, moves them off the plane of their neighbours.

    The ``NOISE_NEAR`` nearest neighbours of each of ``NOISE_PROBES`` points (drawn with a fixed seed) are fitted
    by a plane; the median of their RMS distance to it (scaled by sqrt(k / (k - 3)): the fit takes three degrees
    of freedom) is the noise.  On a curved surface that
    distance grows with the square of the neighbourhood's radius, on a noisy flat one it does not: where the
    median at ``NOISE_FAR`` neighbours exceeds ``CURVED_GROWTH`` times the near one, curvature is what is
    measured, and no noise is read.

    With ``normals``, a probe's neighbours are the nearest of the points on its side of the surface (normals
    within ``SIDE_COS``, among its ``2 * NOISE_FAR`` nearest; where that leaves under half the probes enough of
    them, as without normals): on a thin wall or a shelf the far neighbourhood otherwise reaches the other side,
    which reads as curvature.

    Parameters
    ----------
    points : (N, 3) float, in the unit frame
    normals : (N, 3) float, optional, unit
    """
    if len(points) <= NOISE_FAR:
        return 0.0
    pick = np.random.default_rng(0).choice(len(points), min(len(points), NOISE_PROBES), replace=False)
    idx = cKDTree(points).query(points[pick], k=min(len(points), NOISE_FAR if normals is None else 2 * NOISE_FAR))[1]
    if normals is not None:
        n = np.asarray(normals, dtype=np.float64)
        side = np.einsum("pkd,pd->pk", n[idx], n[pick]) > SIDE_COS
        sided = np.take_along_axis(idx, np.argsort(~side, axis=1, kind="stable"), axis=1)[side.sum(1) >= NOISE_FAR]
        # Normals whose signs disagree leave few probes a side of their own: read as without normals.
        idx = sided if 2 * len(sided) >= len(pick) else idx
    near, far = (_plane_rms(points, idx[:, :k]) for k in (NOISE_NEAR, NOISE_FAR))
    near *= np.sqrt(NOISE_NEAR / (NOISE_NEAR - 3))
    far *= np.sqrt(NOISE_FAR / (NOISE_FAR - 3))
    return float(near) if far <= CURVED_GROWTH * near else 0.0


def _plane_rms(points: np.ndarray, idx: np.ndarray) -> float:
    """The median over the points of the RMS distance of their neighbours ``idx`` (N, k) to their fitted plane."""
    nb = points[idx] - points[idx].mean(1, keepdims=True)
    low = np.linalg.eigvalsh(np.einsum("nki,nkj->nij", nb, nb) / idx.shape[1])[:, 0]
    return float(np.median(np.sqrt(np.maximum(low, 0.0))))


def fitted_normals(points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) the normals of the planes fitted to each point's ``NOISE_FAR`` neighbours, on the side of its
    given normal ``normals`` (N, 3): a noisy scan's own normals (a dense mesh's faces, each tilted by the noise of
    its three corners) scatter by tens of degrees.  And (N,) the points ordered by how well that plane fits
    (best first): seeds inside flat sides grow them whole before a seed near an edge, whose fitted plane leans
    between two sides, grows a sliver of both."""
    idx = cKDTree(points).query(points, k=NOISE_FAR)[1]
    nb = points[idx] - points[idx].mean(1, keepdims=True)
    low, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", nb, nb))
    fitted = vectors[:, :, 0]
    return (fitted * np.where(np.einsum("ij,ij->i", fitted, normals) < 0, -1.0, 1.0)[:, None],
            np.argsort(low[:, 0], kind="stable"))


def flat_only(points: np.ndarray, planes: np.ndarray, labels: np.ndarray, sigma: float, inliers: float
              ) -> tuple[np.ndarray, np.ndarray] | None:
    """A noisy scan's planes (K, 4) (``planar``'s), each fitted again to all the points it took (the seed's fit
    saw only those whose normals agreed), and the plane of each point (N,), without those whose points lie off
    them by an RMS above ``FLAT_RMS`` times the noise ``sigma``: a facet laid over a curved scan holds its points
    within the tolerance too, but spread over its whole width (the sag of the curve), not as the noise spreads them; so
    does a sliver grown from a few points beyond the noise along an edge.  A plane left with fewer than three points
    (the others held by other planes, ``planar._by_normal``) goes too.  None where, without them, more than
    ``1 - inliers`` of the points are unexplained (a curved scan)."""
    mine = labels >= 0
    count = np.bincount(labels[mine], minlength=len(planes))
    planes = np.array([refit(points[labels == k], plane) if count[k] >= 3 else plane for k, plane in enumerate(planes)])
    off = np.abs(np.einsum("ij,ij->i", points[mine], planes[labels[mine], :3]) - planes[labels[mine], 3])
    rms = np.sqrt(np.bincount(labels[mine], weights=off**2, minlength=len(planes)) / np.maximum(count, 1))
    flat = (rms <= FLAT_RMS * sigma) & (count >= 3)
    if (~mine).sum() + count[~flat].sum() > len(points) * (1 - inliers) or not flat.any():
        return None
    return kept_planes(planes, labels, flat)


def kept_planes(planes: np.ndarray, labels: np.ndarray, kept: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``planes`` (K, 4) where ``kept`` (K,) bool, and ``labels`` (N,) numbered among them (-1: none, or a plane
    not kept)."""
    renumber = np.where(kept, np.cumsum(kept) - 1, -1)
    return planes[kept], np.where(labels >= 0, renumber[np.maximum(labels, 0)], -1)


def refit(points: np.ndarray, plane: np.ndarray) -> np.ndarray:
    """(4,) the least-squares plane of ``points`` (M, 3), its normal on the side of ``plane``'s (4,)."""
    centre = points.mean(0)
    n = np.linalg.svd(points - centre, full_matrices=False)[2][-1]
    n = n if n @ plane[:3] >= 0 else -n
    return np.r_[n, n @ centre]
