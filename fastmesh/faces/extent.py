"""A result's bounding box brought to the input's.

A game pipeline places, scales and collides an asset by its box: where a character's feet stand, how tall it is,
what it hits.  The decoder's vertices sit in 7-bit cells and are fitted onto the input's planes, and a rounded end
or a tip the input reaches between two vertices gets cut across, so a result's box can fall short of the input's
by a cell or two (1-2 % of the longest side on held-out characters): the result is a shade too small, and where
it is scaled to the input's box it lies off the input everywhere.

:func:`reach_extent` takes each side of the input's box the mesh falls short of and moves the vertex nearest the
input's outermost point there onto it, or, where no vertex lies near, adds the point as a vertex on the nearest
face (or edge); vertices beyond the box come back onto it.  A point cloud's outermost point counts only with
others around it: a stray sample is no tip.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..tokenizer.grid import CELL
from .meshops import closest_on_triangles, face_normals, point_triangle_distance

# All relative to the input box's longest side.  A side falls short where the mesh stops more than this inside it.
SHORT = 0.25 * CELL
# The vertex nearest the outermost point moves onto it within this; farther, the point is added as a vertex.
NEAR = CELL
# An outermost point farther than this from the mesh is a part the mesh lacks, not a tip it cuts: one vertex
# there would be a spike.
REACH = 4 * CELL
# A point cloud's outermost point has at least this many others within SUPPORT_SPACINGS x the cloud's median
# spacing (the distance from a point to its nearest); the first among the OUTERMOST farthest out that has them
# stands for the side.  A thin tip's samples lie a spacing or two apart; a stray lies farther from all.
SUPPORT_POINTS = 2
SUPPORT_SPACINGS = 3.0
OUTERMOST = 64
MAX_ADDED = 6  # vertices added at most: one a side, each two faces more
# The outermost point lies on a face's edge where its barycentric coordinate opposite the edge is under this.
ON_EDGE = 0.1


def reach_extent(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, supported: bool = True,
                 add: bool = True) -> tuple[np.ndarray, np.ndarray, int]:
    """The mesh's axis-aligned box brought to the box of the input's ``points``.

    Parameters
    ----------
    vertices : (V, 3) float
    faces : (F, 3) int, consistently wound; no two vertices at one position (pinches made one first)
    points : (P, 3) float
        The input's outermost evidence in the frame of ``vertices``: a point cloud's points, a mesh's vertices.
    supported : bool
        A side's outermost point needs ``SUPPORT_POINTS`` others around it (a point cloud's strays).
    add : bool
        Whether a vertex may be added (not where a face count is held).

    Returns
    -------
    vertices : (V', 3) float64, V' <= V + ``MAX_ADDED``, vertices beyond the box on it
    faces : (F', 3) int64, F' <= F + 2 ``MAX_ADDED``, windings kept
    reached : int, sides of the box the mesh fell short of and now reaches
    """
    v = np.array(vertices, dtype=np.float64).reshape(-1, 3)
    f = np.array(faces, dtype=np.int64).reshape(-1, 3)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if not len(f) or len(pts) < 2:
        return v, f, 0
    length = float(np.ptp(pts, axis=0).max())
    tree = cKDTree(pts) if supported else None
    spacing = float(np.median(tree.query(pts, k=2)[0][:, 1])) if supported else 0.0
    v = _clamped(v, f, pts.min(axis=0), pts.max(axis=0))
    outer = _outermost(pts, tree, spacing)  # (3, 2) point index per axis and side, -1: none
    reached = 0
    for axis in range(3):
        for side, sign in enumerate((-1.0, 1.0)):
            i = outer[axis, side]
            if i < 0 or (sign * (pts[i, axis] - v[:, axis])).min() <= SHORT * length:
                continue
            moved = _move_nearest(v, f, pts[i], NEAR * length)
            if moved is None and add:
                moved = _add_vertex(v, f, pts[i], REACH * length)
            if moved is not None:
                v, f = moved
                reached += 1
    return v, f, reached


def _clamped(v: np.ndarray, f: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Vertices beyond the box ``lo`` .. ``hi`` moved onto it, but not those of a face that would turn over or lose
    its area (a thin fin or a corner flattened onto the box).

    A thin tip's samples may stop short of a vertex that lies right; on the held-out clouds the vertices beyond are
    mostly a rim or a cap that overshoots, and the mean CD gains more from the box than it loses there
    (docs/results.md)."""
    out = np.clip(v, lo, hi)
    while True:  # a vertex put back may turn a face of its own over: until none moved is on one
        bad = np.unique(f[_turned(v, f, out, f)])
        bad = bad[(out[bad] != v[bad]).any(axis=1)]
        if not len(bad):
            return out
        out[bad] = v[bad]


def _outermost(points: np.ndarray, tree, spacing: float) -> np.ndarray:
    """(3, 2) int64: per axis, the index of the lowest and the highest point; with a cKDTree ``tree`` of them (a
    point cloud's, ``spacing`` apart at the median), the outermost of the ``OUTERMOST`` farthest out that has
    ``SUPPORT_POINTS`` others within ``SUPPORT_SPACINGS`` spacings, -1 where none has."""
    out = np.full((3, 2), -1, dtype=np.int64)
    radius = SUPPORT_SPACINGS * spacing
    for axis in range(3):
        for side, sign in enumerate((-1.0, 1.0)):
            order = np.argsort(-sign * points[:, axis], kind="stable")[:OUTERMOST]
            if tree is None:
                out[axis, side] = order[0]
                continue
            counts = np.array([len(n) - 1 for n in tree.query_ball_point(points[order], radius)])
            found = np.flatnonzero(counts >= SUPPORT_POINTS)
            if len(found):
                out[axis, side] = order[found[0]]
    return out


def _turned(v: np.ndarray, f: np.ndarray, new_v: np.ndarray, new_f: np.ndarray) -> np.ndarray:
    """(K,) bool: which faces ``new_f`` (K, 3) of ``new_v`` turn over or lose their area against the faces ``f``
    (K, 3) of ``v`` they stand for, pair by pair."""
    return np.einsum("ij,ij->i", face_normals(v, f), face_normals(new_v, new_f)) <= 0


def _move_nearest(v: np.ndarray, f: np.ndarray, point: np.ndarray, near: float
                  ) -> tuple[np.ndarray, np.ndarray] | None:
    """The vertex nearest ``point`` moved onto it where it lies within ``near`` and none of its faces turns over
    or loses its area; None where not."""
    d = np.linalg.norm(v - point, axis=1)
    used = np.zeros(len(v), dtype=bool)
    used[f.ravel()] = True
    d[~used] = np.inf
    i = int(np.argmin(d))
    if d[i] > near:
        return None
    around = f[(f == i).any(axis=1)]
    moved = v.copy()
    moved[i] = point
    return None if _turned(v, around, moved, around).any() else (moved, f)


def _add_vertex(v: np.ndarray, f: np.ndarray, point: np.ndarray, reach: float
                ) -> tuple[np.ndarray, np.ndarray] | None:
    """``point`` added as a vertex where the mesh lies nearest it: its nearest face split in three, or the two
    faces of its nearest edge in two each (``ON_EDGE``); None where the mesh lies farther than ``reach`` or a new
    face would turn over against the one it replaces."""
    tri = v[f]
    dist = point_triangle_distance(np.repeat(point[None], len(f), axis=0), tri)
    j = int(np.argmin(dist))
    if dist[j] > reach:
        return None
    bary = closest_on_triangles(point[None], tri[j][None])[0]
    m = len(v)
    k = int(np.argmin(bary))
    if bary[k] < ON_EDGE:  # the edge opposite corner k
        a, b = f[j, (k + 1) % 3], f[j, (k + 2) % 3]
        on = np.flatnonzero(np.isin(f, (a, b)).sum(axis=1) == 2)
        old, new = [], []
        for face in on:
            r = int(np.flatnonzero((f[face] == a) | (f[face] == b))[0])
            r = r if f[face, (r + 1) % 3] in (a, b) else (r + 2) % 3  # the corner the edge starts at
            u, w, c = f[face, r], f[face, (r + 1) % 3], f[face, (r + 2) % 3]
            old += [face, face]
            new += [(u, m, c), (m, w, c)]
    else:
        a, b, c = f[j]
        old, new = [j, j, j], [(a, b, m), (b, c, m), (c, a, m)]
    out_v = np.concatenate([v, point[None]])
    new = np.array(new, dtype=np.int64)
    if _turned(v, f[old], out_v, new).any():
        return None
    keep = np.ones(len(f), dtype=bool)
    keep[old] = False
    return out_v, np.concatenate([f[keep], new])
