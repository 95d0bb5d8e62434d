"""The noise of a scan, read from its points: how far they lie off the planes of their neighbours where the
surface itself is flat at that scale (``planar`` holds a scan's planes at its own noise)."""

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
