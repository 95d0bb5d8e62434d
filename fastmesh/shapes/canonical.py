"""The frame a shape is generated in: its own, or its oriented bounding box's where that lays its walls along
the axes.

Modellers build along the axes, and the decoder learned from their meshes: a box uploaded at an angle
looks to it like no artist mesh it has seen (its flat walls cross the 7-bit grid diagonally), and comes back
with dozens of vertices along each wall.  :func:`canonical_rotation` finds the rotation that lays the shape's
smallest enclosing box (over its convex hull) along the axes, corrected by the normals of its flat walls, and
the pipeline generates there and turns the result back.  It turns only where that lays clearly more of the
surface's normals along the axes than the input's own frame does: an artist's mesh is left as it is even
where a tighter box exists at some angle (an aircraft's swept wings, a character's pose), and so is a shape
with no flat walls, whose frame does not matter to the decoder.

Of the 24 ways to label the box's axes, the one nearest the input's own is taken, so a shape turned by a
few degrees is turned back by those few degrees, and "up" stays where the input had it.
"""

from __future__ import annotations

import itertools

import numpy as np

from .io import sample_surface
from .shape import Normalization, Shape

# With normals: turn when the box's frame has at least this much more of the surface (the share of the
# normals, area-weighted samples) within ALIGNED_DEGREES of an axis than the input's frame has.
TURN_GAIN = 0.25
ALIGNED_DEGREES = 5.0
# Without normals: turn when the oriented box holds the shape in less than this share of its axis-aligned
# box's volume (a box turned by 2 degrees about one axis fills about 0.94 of it).
TURN_BELOW = 0.97
# Added to the angle of :func:`aligned_share_bound`: floating-point rounding never takes a normal out of it.
BOUND_MARGIN_DEGREES = 0.01
# Normals within this angle of an axis of the box's frame align that frame exactly (:func:`_aligned`).
SNAP_DEGREES = 15.0
# Each box side is padded by this share of the longest before volumes are compared: a flat shape (a
# plane, one triangle) has no volume, yet its turn still shows in the other two sides.
_PAD = 0.01


def _proper_axis_maps() -> np.ndarray:
    """(24, 3, 3) the signed permutation matrices of determinant +1: the rotations of a cube."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            m = np.zeros((3, 3))
            m[range(3), perm] = signs
            if np.linalg.det(m) > 0:
                out.append(m)
    return np.array(out)


_AXIS_MAPS = _proper_axis_maps()


def _padded_volume(extents: np.ndarray) -> float:
    e = np.asarray(extents, dtype=np.float64)
    return float(np.prod(e + _PAD * e.max()))


def canonical_rotation(points: np.ndarray, normals: np.ndarray | None = None,
                       turn_below: float = TURN_BELOW) -> np.ndarray:
    """The rotation that lays ``points`` along the axes, or the identity where they already lie so.

    The box of a point sample's hull is off by a degree or so (the sample misses the corners); where
    the surface's normals gather along the box's axes (flat walls), they set the frame exactly.

    Parameters
    ----------
    points : (N, 3) float
        A shape's vertices or points, in any frame.
    normals : (M, 3) float, optional
        Unit normals of the surface (e.g. of an area-weighted sample), either orientation: with them the turn
        is taken when it lays ``TURN_GAIN`` more of them along the axes (:func:`aligned_share`).
    turn_below : float
        Without normals: turn only when the oriented box's (padded) volume is below this share of the
        axis-aligned box's.

    Returns
    -------
    (3, 3) float64 rotation R (det +1): the shape in the canonical frame is ``points @ R.T``.
    """
    if normals is not None and aligned_share_bound(normals) < aligned_share(normals) + TURN_GAIN:
        return np.eye(3)  # no frame could lay enough of the normals along its axes: the box is not looked for
    rot = _box_rotation(points)
    if rot is None:
        return np.eye(3)
    if normals is None:
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if _padded_volume(np.ptp(p @ rot.T, axis=0)) >= turn_below * _padded_volume(np.ptp(p, axis=0)):
            return np.eye(3)
    else:
        for _ in range(2):  # the second pass snaps the normals the first one brought within reach
            rot = _aligned(rot, normals)
        if aligned_share(normals @ rot.T) < aligned_share(normals) + TURN_GAIN:
            return np.eye(3)
    # Of the 24 labelings of the box's axes, the one nearest the input's own (largest trace: least angle).
    return _AXIS_MAPS[int(np.argmax(np.einsum("kij,ji->k", _AXIS_MAPS, rot)))] @ rot


def aligned_share(normals: np.ndarray, degrees: float = ALIGNED_DEGREES) -> float:
    """The share of ``normals`` (M, 3) within ``degrees`` of an axis (either direction)."""
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    n = n[np.isfinite(n).all(1)]
    if len(n) == 0:
        return 0.0
    length = np.maximum(np.linalg.norm(n, axis=1), 1e-12)
    return float((np.abs(n).max(1) / length >= np.cos(np.radians(degrees))).mean())


def aligned_share_bound(normals: np.ndarray, degrees: float = ALIGNED_DEGREES) -> float:
    """An upper bound on :func:`aligned_share` of ``normals`` (M, 3) turned by any rotation.

    The normals within ``degrees`` of an axis (either direction) lie within twice ``degrees`` of any one of
    them (either direction), so each of the three axes holds at most the most normals found within twice
    ``degrees`` of one normal.  Smooth shapes (no flat walls) read a few per cent: far below what a turn
    must gain, which :func:`canonical_rotation` then knows without looking for the box.
    """
    from scipy.spatial import cKDTree

    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    n = n[np.isfinite(n).all(1)]
    length = np.linalg.norm(n, axis=1)
    u = n[length > 0] / length[length > 0, None]
    if len(u) == 0:
        return 0.0
    # Chord length of the angle, with a margin for rounding; a normal and its opposite are never both near.
    chord = 2.0 * np.sin(np.radians(2.0 * degrees + BOUND_MARGIN_DEGREES) / 2.0)
    near = cKDTree(np.concatenate([u, -u])).query_ball_point(u, chord, return_length=True)
    return min(1.0, 3.0 * float(np.max(near)) / len(n))


def _box_rotation(points: np.ndarray) -> np.ndarray | None:
    """(3, 3) the rotation onto the axes of the points' smallest enclosing box (det +1), None where the
    points enclose nothing (fewer than four, flat in a way qhull refuses, not finite)."""
    import trimesh
    from scipy.spatial import QhullError

    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(p) < 4 or not np.isfinite(p).all():
        return None
    p = p - p.mean(0)  # the box of the shape, not of a far origin, in units of its size: any scale works
    with np.errstate(over="ignore"):
        size = float(np.abs(p).max())
    if not (np.isfinite(size) and size > 0):
        return None
    try:
        to_box = trimesh.bounds.oriented_bounds(p / size)[0]
    except (QhullError, ValueError, TypeError, np.linalg.LinAlgError):  # flat or degenerate: no box to take
        return None
    rot = np.asarray(to_box[:3, :3], dtype=np.float64)
    if np.linalg.det(rot) < 0:  # a reflection among the box's labelings: flip one axis
        rot = rot * np.array([[1.0], [1.0], [-1.0]])
    return rot


def _aligned(rot: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """``rot`` (3, 3) corrected so that the ``normals`` (M, 3) it takes near an axis lie on it (Kabsch).

    Only where normals gather near at least two axes (one alone leaves the turn about it free)."""
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3) @ rot.T
    n = n[np.isfinite(n).all(1)]
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    axis = np.abs(n).argmax(1)
    near = np.abs(n[np.arange(len(n)), axis]) >= np.cos(np.radians(SNAP_DEGREES))
    if (np.bincount(axis[near], minlength=3) >= 0.05 * len(n)).sum() < 2:
        return rot
    target = np.zeros_like(n[near])
    target[np.arange(near.sum()), axis[near]] = np.sign(n[near, axis[near]])
    u, _, vt = np.linalg.svd(target.T @ n[near])  # the turn q taking n onto target: q = u diag vt
    q = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    return q @ rot


def rotate_shape(shape: Shape, rotation: np.ndarray) -> Shape:
    """``shape`` turned by ``rotation`` (3, 3) about its frame's origin: vertices and normals, faces shared."""
    r = np.asarray(rotation, dtype=np.float64)
    normals = None if shape.normals is None else np.asarray(shape.normals, dtype=np.float64) @ r.T
    return Shape(vertices=np.asarray(shape.vertices, dtype=np.float64) @ r.T, faces=shape.faces, normals=normals)


def turned_degrees(rotation: np.ndarray) -> float:
    """The angle of ``rotation`` (3, 3), in degrees."""
    c = (np.trace(np.asarray(rotation, dtype=np.float64)) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def frame_normals(shape: Shape, n: int = 4096, seed: int = 0) -> np.ndarray:
    """(<= n, 3) normals that stand for ``shape``'s surface in :func:`canonical_rotation`: a mesh's at
    ``n`` area-weighted samples (fixed seed), a point cloud's own (at most ``n`` of them)."""
    if shape.faces is not None:  # sampled in the unit cube: the areas of far-apart coordinates overflow
        unit = Normalization.fit(shape.vertices).apply(shape.vertices)
        return sample_surface(shape, n, seed=seed, vertices=unit)[1].astype(np.float64)
    nrm = np.asarray(shape.normals, dtype=np.float64)
    if len(nrm) > n:
        nrm = nrm[np.random.default_rng(seed).choice(len(nrm), size=n, replace=False)]
    return nrm
