"""Which way a point cloud's normals point: outward where the points enclose a volume, whatever signs they came with.

Scanners, photogrammetry and PCA give normals of arbitrary sign; the closure's winding-number test
(``faces.closure.winding_closed_share``), the plane rebuild (``shapes.planar``) and the networks (trained on the
outward normals of artist meshes) read the sign.  The points are voxelised at about their spacing, the occupied
voxels grown by one, and the empty voxels that the grid's border cannot reach are the inside.  A point whose normal
has the inside on one side and the outside on the other gets the outward sign; the others (open sheets, parts
thinner than a voxel) take the sign of their oriented neighbours with normals alike, or keep their own.  Only mixed
normals are turned: ones that agree already are read as they are.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from .shape import Normalization, Shape

# The voxel is a factor of the median distance to the K-th nearest point, at least 1 / MAX_SIDE of the longest side
# (the grid stays at most MAX_SIDE^3: bounded memory).  The finer grid first: it tells more points, and parts
# thinner than a coarse voxel; where sampling gaps let the outside in (no inside is left), the coarser one.  Gaps
# between neighbours close once the occupied voxels grow by one.
K = 8
FACTORS = (0.7, 1.0)
MAX_SIDE = 160
MIN_SIDE = 24  # a coarser grid cannot hold an inside behind a grown shell
# Each side of a point is read this many voxels along its normal: past the grown shell around the point.
REACH = 3.0
# Points read for the voxel size (the median of a subsample), and rounds of sign propagation for undecided ones.
SAMPLE = 20000
ROUNDS = 8
NEIGHBOURS = 8
ALIKE = 0.7  # |cos| of the angle between two normals for one to pass its sign on
# The normals are turned only where they are mixed: more than this share of the points that can tell point
# inward, and more than this share outward.  Normals that agree stay exactly as given, outward or inward (Quake's
# formats wind their faces the other way: the networks learned from both, the winding-number test reads both).
MIXED_SHARE = 0.1
# ... and where at least this share of the points can tell (a few readings near a thin part are no evidence).
TOLD_SHARE = 0.1


def _grid(p: np.ndarray, factor: float) -> tuple[np.ndarray, float, np.ndarray]:
    """Labels of a voxel grid over unit-cube points ``p`` (N, 3) at ``factor`` times their spacing: 0 shell,
    1 outside, 2 inside; the voxel size and the grid's origin."""
    rng = np.random.default_rng(0)
    some = p[rng.choice(len(p), size=min(len(p), SAMPLE), replace=False)]
    d = cKDTree(some).query(some, k=min(K + 1, len(some)))[0][:, -1]
    # A subsample's spacing is sqrt(N / n) times the whole cloud's (points per area).
    voxel = float(np.clip(factor * np.median(d) * np.sqrt(len(some) / len(p)), 1.0 / MAX_SIDE, 1.0 / MIN_SIDE))
    origin = p.min(0) - 3 * voxel
    side = np.ceil((p.max(0) - origin) / voxel).astype(int) + 4
    cells = np.floor((p - origin) / voxel).astype(int)
    shell = np.zeros(side, dtype=bool)
    shell[tuple(cells.T)] = True
    shell = ndimage.binary_dilation(shell, structure=np.ones((3, 3, 3), dtype=bool))
    labels, _ = ndimage.label(~shell)
    border = np.unique(np.concatenate([labels[[0, -1]].ravel(), labels[:, [0, -1]].ravel(),
                                       labels[:, :, [0, -1]].ravel()]))
    out = np.zeros(side, dtype=np.int8)
    out[~shell] = 2
    out[np.isin(labels, border[border > 0])] = 1
    return out, voxel, origin


def outward_signs(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(N,) +1 where a normal points out of the volume the points enclose, -1 where it points in, 0 where its two
    sides do not tell (an open sheet, a part thinner than a voxel, no volume at all).

    Parameters
    ----------
    points : (N, 3) float
    normals : (N, 3) float, unit
    """
    p = Normalization.fit(points).apply(np.asarray(points, dtype=np.float64))
    n = np.asarray(normals, dtype=np.float64)
    for factor in FACTORS:
        labels, voxel, origin = _grid(p, factor)
        hi = np.array(labels.shape) - 1

        def read(q, labels=labels, voxel=voxel, origin=origin, hi=hi):
            return labels[tuple(np.clip(np.floor((q - origin) / voxel).astype(int), 0, hi).T)]

        front, back = read(p + REACH * voxel * n), read(p - REACH * voxel * n)
        sign = np.where((front == 1) & (back == 2), 1, np.where((front == 2) & (back == 1), -1, 0)).astype(np.int8)
        if np.count_nonzero(sign) >= TOLD_SHARE * len(sign):
            break
    return sign


def _spread(p: np.ndarray, n: np.ndarray, sign: np.ndarray) -> np.ndarray:
    """``sign`` (N,) with its zeros filled from their neighbours: each undecided point takes the sign that makes
    its normal agree with most of its decided neighbours whose normals are alike, for a few rounds."""
    idx = cKDTree(p).query(p, k=min(NEIGHBOURS + 1, len(p)))[1][:, 1:]
    sign = sign.astype(np.float64)
    for _ in range(ROUNDS):
        todo = np.flatnonzero(sign == 0)
        if len(todo) == 0:
            break
        nb = idx[todo]
        dot = np.einsum("ti,tki->tk", n[todo], n[nb])
        vote = (np.where(np.abs(dot) >= ALIKE, np.sign(dot), 0.0) * sign[nb]).sum(1)
        if not vote.any():
            break
        sign[todo] = np.sign(vote)
    return sign


def _told(points: np.ndarray, normals: np.ndarray) -> np.ndarray | None:
    """:func:`outward_signs` where at least ``TOLD_SHARE`` of the points tell, else None (also for fewer than
    4 K points): the one rule both :func:`oriented` and :func:`outward` turn by."""
    if len(points) < 4 * K:
        return None
    sign = outward_signs(points, normals)
    return sign if np.count_nonzero(sign) >= TOLD_SHARE * len(sign) else None


def oriented(shape: Shape) -> Shape:
    """``shape`` with mixed normals turned outward (see the module's docstring and ``MIXED_SHARE``); a mesh, a point
    cloud without normals, or one whose normals agree (all outward or all inward where they can tell) comes back
    as it is."""
    if shape.faces is not None or shape.normals is None:
        return shape
    n = np.asarray(shape.normals, dtype=np.float64)
    sign = _told(shape.vertices, n)
    if sign is None:
        return shape
    told, inward = np.count_nonzero(sign), np.count_nonzero(sign < 0)
    if min(inward, told - inward) <= MIXED_SHARE * told:
        return shape
    return Shape(vertices=shape.vertices, normals=_turned(shape.vertices, n, sign))


def outward(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(N, 3) ``normals`` turned outward wherever the points enclose a volume, whatever share points in: for normals
    whose signs are our own guess (``io.estimate_normals``), not the input's.  As they are where under
    ``TOLD_SHARE`` of the points can tell (no surface enclosing a volume: a sheet, a blob of points)."""
    sign = _told(points, normals)
    return normals if sign is None else _turned(points, np.asarray(normals, dtype=np.float64), sign)


def _turned(points: np.ndarray, normals: np.ndarray, sign: np.ndarray) -> np.ndarray:
    """``normals`` times the signs told (``outward_signs``), spread to the undecided ones (:func:`_spread`)."""
    sign = _spread(Normalization.fit(points).apply(points), normals, sign)
    return normals * np.where(sign < 0, -1.0, 1.0)[:, None]
