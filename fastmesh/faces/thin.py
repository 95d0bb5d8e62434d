"""Thin parts for the solid face stage: vertices on both sides of a part the decoded vertices cannot enclose.

A leg, a horn or a boom thinner than a cell of the vertex grid has at most one decoded vertex across it: no
Delaunay cell of those vertices lies inside it, and the cut (``fastmesh.faces.solid``) loses it.  The input's own
samples on such a part (:func:`lost_samples`, those the cut left farther than ``solid.LOST_LIMITS`` support
limits) are added to the vertices, a few per part and on every side of it (:func:`thin_vertices`): the cells
between its sides then lie inside it, and the cut can keep it as a thin closed part.  Between samples nearer each
other than their spacing the winding numbers are a sum of a few dipoles and cannot tell inside from outside; a
short cell that the normals of its sample corners all face away from is inside (:func:`facing_away`).  The cut with
the added vertices (:func:`thin_picks`) comes back where it loses fewer samples and lies no farther from them
(``solid.with_thin_parts``).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

# The input samples added as vertices: at most one per cube of this many support limits (``support.support_limit``)
# a side and per side of a part (the sign of each normal component): a thin part's two sides both keep theirs.
THIN_SPACING = 2.0
# A cell between added samples is inside where they all face away from it (``facing_away``) and no edge of it is
# longer than this many times their spacing.
THIN_REACH = 2.0
# At most this share of the decoded vertices' count is added (and at least THIN_MOST may be): the spacing grows by
# THIN_GROWTH, up to THIN_ROUNDS times, until it is; none is added where it is not then.
THIN_SHARE = 0.25
THIN_MOST = 128
THIN_GROWTH = 1.25
THIN_ROUNDS = 10
# The samples a part needs before it is given vertices: fewer are noise or a sliver the cut may well leave out.
THIN_MIN_SAMPLES = 3
# The lattice ``farther_than`` lays on a face has at most this many steps along its longest side.
LATTICE_STEPS = 8


def thin_vertices(points: np.ndarray, normals: np.ndarray, spacing: float) -> np.ndarray:
    """(X,) int, the ``points`` (P, 3) thinned to one per cube of side ``spacing`` and per side, the side being the
    signs of the ``normals`` (P, 3) components (one point of each such group: the nearest its group's mean)."""
    if len(points) < THIN_MIN_SAMPLES:
        return np.zeros(0, dtype=np.int64)
    p = np.asarray(points, dtype=np.float64)
    side = np.sign(np.round(np.asarray(normals, dtype=np.float64) * 1.5))  # -1, 0, 1 per component
    key = np.concatenate([np.floor((p - p.min(0)) / max(spacing, 1e-300)), side], axis=1)
    _, group = np.unique(key, axis=0, return_inverse=True)
    group = group.reshape(-1)
    mean = np.stack([np.bincount(group, p[:, i]) for i in range(3)], axis=1) / np.bincount(group)[:, None]
    d = ((p - mean[group]) ** 2).sum(1)
    order = np.lexsort((d, group))
    first = order[np.r_[True, group[order][1:] != group[order][:-1]]]
    return np.sort(first)


def facing_away(vertices: np.ndarray, tets: np.ndarray, first: int, normals: np.ndarray, reach: float
                ) -> np.ndarray:
    """(K,) bool, the cells ``tets`` (K, 4), no edge longer than ``reach``, with at least two corners among the added
    samples (``vertices[first:]``, normals ``normals`` (X, 3)) whose normals all point away from the cell's centroid:
    a cell between the sides of a part thinner than the samples' spacing, inside it, which the winding numbers
    there (a sum of a few dipoles nearer than their spacing) cannot tell.  A longer cell reaches past the part."""
    corners = vertices[tets]
    edge = np.linalg.norm(corners[:, [0, 0, 0, 1, 1, 2]] - corners[:, [1, 2, 3, 2, 3, 3]], axis=2).max(1)
    centre = corners.mean(1)
    added = (tets >= first) & (tets < first + len(normals))
    n = normals[np.clip(tets - first, 0, len(normals) - 1)]  # (K, 4, 3)
    away = np.einsum("kcd,kcd->kc", n, vertices[tets] - centre[:, None]) > 0
    return (added.sum(1) >= 2) & np.all(away | ~added, axis=1) & (edge <= reach)


def lost_samples(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, tol: float) -> np.ndarray:
    """(P,) bool, the ``points`` (P, 3) farther than ``tol`` from the surface (``vertices`` (N, 3), ``faces``
    (F, 3); all where it has none)."""
    if not len(faces):
        return np.ones(len(points), dtype=bool)
    return farther_than(points, vertices, faces, tol)


def farther_than(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, tol: float) -> np.ndarray:
    """(P,) bool, the ``points`` (P, 3) farther than ``tol`` from every face (F, 3) of ``vertices`` (N, 3).

    A point within ``tol`` of a lattice of points on the faces (spaced about ``tol``) is within it of the faces;
    only the others are measured exactly (``meshops.distance_to_triangles``, which weighs every face's box
    against every point: most of the cost where most points lie on the surface)."""
    from .meshops import distance_to_triangles

    tri = vertices[faces]
    longest = np.linalg.norm(tri - tri[:, [1, 2, 0]], axis=2).max(1)
    steps = np.clip(np.ceil(longest / max(tol, 1e-300)), 1, LATTICE_STEPS).astype(np.int64)
    lattice = [vertices]
    for k in np.unique(steps):
        i, j = np.nonzero(np.add.outer(np.arange(k + 1), np.arange(k + 1)) <= k)
        w = np.stack([k - i - j, i, j], axis=1) / k  # (L, 3) barycentric
        lattice.append(np.einsum("lc,fcd->fld", w, tri[steps == k]).reshape(-1, 3))
    near = cKDTree(np.concatenate(lattice)).query(points, distance_upper_bound=tol)[0] <= tol
    out = np.zeros(len(points), dtype=bool)
    if (~near).any():
        out[~near] = distance_to_triangles(points[~near], vertices, faces) > tol
    return out


def thin_picks(points: np.ndarray, normals: np.ndarray, lost: np.ndarray, limit: float, count: int
               ) -> tuple[np.ndarray | None, float]:
    """The ``lost`` (P,) bool samples of ``points`` (P, 3) to add as vertices (their indices; None for none) and
    their spacing (:func:`thin_vertices`).

    None where fewer than ``THIN_MIN_SAMPLES`` are lost, or where even ``THIN_ROUNDS`` growths of the spacing
    (from ``THIN_SPACING`` support limits ``limit``) leave more than ``THIN_SHARE`` of the ``count`` decoded
    vertices (and ``THIN_MOST``): a shape the decoded vertices lost whole is not rebuilt from its samples."""
    spacing = THIN_SPACING * limit
    if lost.sum() < THIN_MIN_SAMPLES:
        return None, spacing
    most = max(THIN_MOST, int(THIN_SHARE * count))
    pick = thin_vertices(points[lost], normals[lost], spacing)
    for _ in range(1, THIN_ROUNDS):
        if len(pick) <= most:
            break
        spacing *= THIN_GROWTH
        pick = thin_vertices(points[lost], normals[lost], spacing)
    if len(pick) > most:
        return None, spacing
    return np.flatnonzero(lost)[pick], spacing
