"""The straight edges of a flat patch of points, in any direction: where a sheet cut at an angle stops.

``open_planar`` ends each plane's faces where its own points stop.  Along or across its neighbours' lines the
direction is the artist's; a gusset's slope or a plate's slanted end runs along no other edge, so its direction comes
from the points themselves: from each edge of their convex outline, refined on the outermost points near it and
then on the line that leaves the least room between the points and it (:func:`outline_ways`).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from .arrangement import plane_basis

FIT_ROUNDS = 3  # fits of a hull edge's direction to the outermost points near it (a wedge-shaped band narrows)
TILT_DEGREES = 3.0  # how far the supporting line is turned from that fit, either way (in steps of 0.05)


def outline_ways(points: np.ndarray, n: np.ndarray, reach: float, alike_cos: float) -> list[np.ndarray]:
    """Unit directions (3,) in the plane of normal ``n`` (3,), out of its ``points`` (P, 3) across the straight
    stretches of their convex outline, one for those within ``alike_cos`` of each other.

    Each edge of the points' convex hull in the plane gives a first direction, fitted in turn to the outermost
    points in each ``reach`` of the band within ``reach`` of their furthest (:func:`_envelope_way`); it is kept where
    the points lie along all of its stretch (:func:`_straight`, not a hull edge across a notch), as the direction
    whose supporting line leaves the least room between the points and it (:func:`_supporting`).
    """
    basis = plane_basis(n)
    flat = points @ basis
    try:
        hull = ConvexHull(flat)
    except (QhullError, ValueError):  # too few points, or all on one line
        return []
    out: list[np.ndarray] = []
    for a, b in hull.simplices:
        t = flat[b] - flat[a]
        w = np.array([t[1], -t[0]]) / np.linalg.norm(t)
        if ((flat - flat[a]) @ w > 1e-12).any():
            w = -w
        for _ in range(FIT_ROUNDS):
            w = _envelope_way(flat, w, reach)
        if _straight(flat, w, reach) and all(basis @ w @ o < alike_cos for o in out):
            out.append(basis @ _supporting(flat, w, reach))
    return out


def _envelope_way(flat: np.ndarray, w: np.ndarray, reach: float) -> np.ndarray:
    """(2,) the unit normal, turned toward ``w`` (2,), of the line fitted to the outermost of the 2D points ``flat``
    (P, 2) across ``w`` in each stretch ``reach`` long of the band within ``reach`` of their furthest: the outline's
    edge, not the band's middle (a band across a hull edge a little off the points' edge is a wedge); ``w`` where
    the band spans fewer than three stretches."""
    across = flat @ w
    band = flat[across > across.max() - reach]
    t = band @ np.array([-w[1], w[0]])
    bins = ((t - t.min()) / reach).astype(int)
    order = np.lexsort((band @ w, bins))
    last = np.r_[bins[order][1:] != bins[order][:-1], True]
    outer = band[order[last]]
    if len(outer) < 3:
        return w
    along = np.linalg.svd(outer - outer.mean(0), full_matrices=False)[2][0]
    normal = np.array([along[1], -along[0]])
    return normal if normal @ w > 0 else -normal


def _straight(flat: np.ndarray, w: np.ndarray, reach: float) -> bool:
    """Whether the 2D points ``flat`` (P, 2) within ``reach`` of their furthest across ``w`` (2,) lie along all of
    their stretch (each of its lengths of two ``reach`` holds one at least), not only at the ends of a hull edge
    across a notch."""
    across = flat @ w
    t = flat[across > across.max() - reach] @ np.array([-w[1], w[0]])
    held = np.unique(((t - t.min()) / (2 * reach)).astype(int))
    return len(held) >= 2 and len(held) == held[-1] + 1


def _supporting(flat: np.ndarray, w: np.ndarray, reach: float) -> np.ndarray:
    """(2,) the direction within ``TILT_DEGREES`` of ``w`` (2,) whose supporting line of the 2D points ``flat``
    (P, 2) lies nearest, on average, to those within two ``reach`` of ``w``'s: points sampled up to a straight edge
    most likely stop under the line that leaves the least room between them and it, where a line fitted through the
    outermost points scatters with them (a gusset's slope a degree off moves its sharp corners a percent)."""
    across = flat @ w
    band = flat[across > across.max() - 2 * reach]
    turn = np.radians(np.linspace(-TILT_DEGREES, TILT_DEGREES, int(40 * TILT_DEGREES) + 1))
    ways = np.c_[np.cos(turn) * w[0] - np.sin(turn) * w[1], np.sin(turn) * w[0] + np.cos(turn) * w[1]]  # (T, 2)
    room = (flat @ ways.T).max(0) - (band @ ways.T).mean(0)
    return ways[room.argmin()]
