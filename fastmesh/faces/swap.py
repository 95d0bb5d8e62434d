"""Edges turned where the input surface runs along the other diagonal.

Two triangles (a, b, c) and (b, a, d) that share the edge a-b cover the same four corners as (a, d, c) and
(d, b, c), which share c-d instead.  Where the face model chose the diagonal that cuts across the input (a
limb's round side spanned flat, a fold, a sliver from one part to the next), the other one lies nearer it, and
turning the edge fits the input better with every vertex where it was: the edge swap of mesh optimization
(Hoppe et al. 1993), scored against the input samples.  A pair's misfit is the distance of its surface to the
input (its face samples' mean distance to the tangent plane of the nearest input point, times its area) plus
the distance back from the input points nearest to it (each standing for its share of the input's area); each
round turns the pairs whose misfit falls the most, no two sharing a face.  Only edges of two faces wound alike
turn, never onto an edge the mesh has, so a closed mesh stays closed and an edge-manifold one edge-manifold;
nor does a pair whose four corners do not bound a convex quad (one turned triangle would fold back over the
other), and with ``uncrossed`` a turn that makes a face cross another is turned back.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .crossings import crossing_faces
from .meshops import face_normals, point_triangle_distance, triangle_areas
from .support import barycentric_grid, face_samples

ROUNDS = 6  # rounds of turns; each sees the turns of the one before (most pairs settle in two or three)
# A pair turns only where its misfit falls by more than this share of it: two ways of cutting one flat quad fit
# alike, and the face model's choice stays where the input does not prefer the other.
MIN_GAIN = 0.001
MIN_AREA = 1e-12  # neither new triangle may be thinner than this share of the mesh's area
# Nor does a pair turn for a fall below this share of the mesh's area x its size: rounding, where both cuts fit.
FLOOR = 1e-9
# A face sample farther than this many median point spacings from its nearest input point is off the sampled
# surface (across a gap), whatever its tangent plane says: the distance beyond counts too.
REACH = 4.0
# The input samples a pair is measured against, at most: the density of the point clouds this was tuned on (a
# mesh input's 32,768 samples cost four times as much and turn the same edges).
POINTS = 8192
GRID = 3  # face samples per edge of the barycentric grid a face is measured at: 6 points inside each triangle
_BARY = barycentric_grid(GRID)


def swap_edges(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, normals: np.ndarray,
               rounds: int = ROUNDS, min_gain: float = MIN_GAIN, uncrossed: bool = False) -> tuple[np.ndarray, int]:
    """The mesh's edges turned where the other diagonal of their two triangles fits the input better.

    Parameters
    ----------
    vertices : (V, 3) float
    faces : (F, 3) int, consistently wound where it is a surface; pinched vertices as one vertex
    points, normals : (P, 3) float
        Samples of the input surface, in the frame of ``vertices``, and their unit normals (either sign); every
        k-th of them where there are more than ``POINTS``.
    rounds, min_gain : see ``ROUNDS`` and ``MIN_GAIN``
    uncrossed : bool
        A turn whose triangles then cross another face is turned back (:func:`_uncrossed`): a surface free of
        crossings (the boundary of a solid) stays free of them.

    Returns
    -------
    faces : (F, 3) int64, the same vertices; windings kept
    turned : int, edges turned (an edge may turn in several rounds)
    """
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3).copy()
    step = -(-len(points) // POINTS)  # every step-th sample: a uniform sample stays uniform
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)[::step]
    if len(f) < 2 or len(pts) == 0:
        return f, 0
    surface = _Surface(pts, np.asarray(normals, dtype=np.float64).reshape(-1, 3)[::step])
    area = triangle_areas(v, f).sum()
    per_point, turned = area / len(pts), 0
    floor = FLOOR * area * float(np.ptp(v, axis=0).max())
    changed = np.ones(len(f), dtype=bool)  # faces turned in the round before: only pairs touching them may gain
    for _ in range(rounds):
        pairs = turnable(f)
        pairs = pairs[changed[pairs[:, 4]] | changed[pairs[:, 5]]]
        if len(pairs) == 0:
            break
        old, new = pairs_before_after(pairs)
        nearest = _nearest_face(v, f, pts)
        before = _misfit(v, old, surface, nearest, pairs[:, 4:], per_point)
        after = _misfit(v, new, surface, nearest, pairs[:, 4:], per_point)
        thick = triangle_areas(v, new.reshape(-1, 3)).reshape(-1, 2).min(1) > MIN_AREA * area
        gain = before - after
        better = np.flatnonzero(thick & _unfolded(v, old, new) & (gain > min_gain * before) & (gain > floor))
        before_round = f.copy()
        done = _turn(f, pairs, new, better[np.argsort(-gain[better], kind="stable")])
        if uncrossed:
            done = done[_uncrossed(v, f, before_round, pairs[done, 4:])]
        changed = np.zeros(len(f), dtype=bool)
        changed[pairs[done, 4:].reshape(-1)] = True
        turned += int(changed.sum()) // 2
        if not changed.any():
            break
    return f, turned


def turnable(faces: np.ndarray) -> np.ndarray:
    """(E, 6) int64 rows a, b, c, d, f1, f2: each edge a-b in exactly two faces, f1 = (a, b, c) and
    f2 = (b, a, d) (wound alike), whose other diagonal c-d is not an edge of the mesh (c != d)."""
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    n = int(f.max()) + 1
    a, b, opp = f.reshape(-1), f[:, [1, 2, 0]].reshape(-1), f[:, [2, 0, 1]].reshape(-1)
    face = np.repeat(np.arange(len(f)), 3)
    edge = np.minimum(a, b) * n + np.maximum(a, b)
    keys, counts = np.unique(edge, return_counts=True)
    directed = a * n + b
    order = np.argsort(directed)
    at = np.minimum(np.searchsorted(directed[order], b * n + a), len(f) * 3 - 1)
    twin = order[at]
    i = np.flatnonzero((a < b) & (directed[twin] == b * n + a)
                       & (counts[np.searchsorted(keys, edge)] == 2))
    j = twin[i]
    c, d = opp[i], opp[j]
    other = np.minimum(c, d) * n + np.maximum(c, d)
    ok = (c != d) & ~np.isin(other, keys)
    return np.stack([a[i], b[i], c, d, face[i], face[j]], axis=1)[ok]


def pairs_before_after(pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(E, 2, 3) the two triangles of each pair (:func:`turnable`'s rows) as they are and turned."""
    a, b, c, d = pairs[:, :4].T
    old = np.stack([np.stack([a, b, c], 1), np.stack([b, a, d], 1)], 1)
    new = np.stack([np.stack([a, d, c], 1), np.stack([d, b, c], 1)], 1)
    return old, new


def _unfolded(vertices: np.ndarray, old: np.ndarray, new: np.ndarray) -> np.ndarray:
    """(E,) bool, the pairs whose turned triangles ``new`` (E, 2, 3) both face the way the pair did (``old``: the
    sum of its two normals): where the four corners do not bound a convex quad, one turned triangle lies folded
    back over the other, a sliver showing its back that crosses no face it does not share a corner with."""
    was = face_normals(vertices, old.reshape(-1, 3)).reshape(-1, 2, 3).sum(1)
    return (np.einsum("eki,ei->ek", face_normals(vertices, new.reshape(-1, 3)).reshape(-1, 2, 3), was) > 0).all(1)


def _nearest_face(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(P,) the face each input point lies nearest (by the nearest of its face samples)."""
    samples = face_samples(vertices, faces, _BARY)  # (F, K, 3)
    _, idx = cKDTree(samples.reshape(-1, 3)).query(points)
    return idx // samples.shape[1]


class _Surface:
    """The input samples with their tangent planes: the distance of a point to the sampled surface."""

    def __init__(self, points: np.ndarray, normals: np.ndarray):
        self.points, self.normals, self.tree = points, normals, cKDTree(points)
        some = points[:: max(1, len(points) // 2048)]
        gaps = self.tree.query(some, k=2)[0][:, 1] if len(points) > 1 else np.zeros(1)
        self.reach = REACH * float(np.median(gaps))

    def distance(self, q: np.ndarray) -> np.ndarray:
        """(N,) the distance of each point ``q`` (N, 3) to its nearest sample's tangent plane, plus how much
        farther than ``reach`` that sample lies: on a flat part, how the part is cut does not matter."""
        dist, idx = self.tree.query(q)
        plane = np.abs(np.einsum("nd,nd->n", q - self.points[idx], self.normals[idx]))
        return plane + np.maximum(dist - self.reach, 0.0)


def _misfit(vertices: np.ndarray, tris: np.ndarray, surface: _Surface, nearest: np.ndarray, owners: np.ndarray,
            per_point: float) -> np.ndarray:
    """(E,) each pair's misfit: its surface's distance to the input (face samples' mean distance x area) plus
    the input points nearest its two faces ``owners`` (E, 2) in the mesh as it is, their distance to the pair's
    triangles ``tris`` (E, 2, 3) x ``per_point``."""
    flat, points = tris.reshape(-1, 3), surface.points
    samples = face_samples(vertices, flat, _BARY)
    dist = surface.distance(samples.reshape(-1, 3)).reshape(len(flat), -1).mean(1)
    stray = (dist * triangle_areas(vertices, flat)).reshape(-1, 2).sum(1)
    order = np.argsort(nearest, kind="stable")
    sorted_faces = nearest[order]
    missed = np.zeros(len(tris))
    for owner in owners.T:
        lo, hi = np.searchsorted(sorted_faces, owner, "left"), np.searchsorted(sorted_faces, owner, "right")
        pair = np.repeat(np.arange(len(tris)), hi - lo)
        if len(pair) == 0:
            continue
        pos = np.arange(len(pair)) - np.repeat(np.cumsum(hi - lo) - (hi - lo), hi - lo) + np.repeat(lo, hi - lo)
        p = points[order[pos]]
        near = np.minimum(point_triangle_distance(p, vertices[tris[pair, 0]]),
                          point_triangle_distance(p, vertices[tris[pair, 1]]))
        np.add.at(missed, pair, near)
    return stray + missed * per_point


def _turn(faces: np.ndarray, pairs: np.ndarray, new: np.ndarray, order: np.ndarray) -> np.ndarray:
    """Turn the pairs in ``order`` (best first) in place in ``faces``, none with a face already turned this
    round and no new edge made twice; (T,) int64, the pairs turned."""
    used = np.zeros(len(faces), dtype=bool)
    made: set[tuple[int, int]] = set()
    done = []
    for e in order.tolist():
        f1, f2 = int(pairs[e, 4]), int(pairs[e, 5])
        edge = tuple(sorted((int(pairs[e, 2]), int(pairs[e, 3]))))
        if used[f1] or used[f2] or edge in made:
            continue
        used[f1] = used[f2] = True
        made.add(edge)
        faces[f1], faces[f2] = new[e, 0], new[e, 1]
        done.append(e)
    return np.asarray(done, dtype=np.int64)


def _uncrossed(vertices: np.ndarray, faces: np.ndarray, before: np.ndarray, turned: np.ndarray) -> np.ndarray:
    """Turn back, in place in ``faces`` (F, 3), each pair of ``turned`` (T, 2: its two faces) whose triangles
    cross another face, to its two faces in ``before`` (F, 3), until no turned pair's do; (T,) bool, the pairs
    that stay turned.  A pair turned back lies as it lay before the round, so it crosses only what it did then."""
    kept = np.ones(len(turned), dtype=bool)
    for _ in range(len(turned)):
        among = np.zeros(len(faces), dtype=bool)
        among[turned[kept].reshape(-1)] = True
        bad = crossing_faces(vertices, faces, among=among)
        back = kept & bad[turned].any(1)
        if not back.any():
            break
        kept &= ~back
        faces[turned[back].reshape(-1)] = before[turned[back].reshape(-1)]
    return kept
