"""Faces checked against the input surface.

The face model connects vertices it believes share a triangle; when it is wrong, the triangle
spans empty space (two nearby parts boxed together, a spike to a stray vertex).  The input shape
tells those apart from real faces: a real face lies on the sampled surface, a wrong one leaves
it.  :func:`support_distance` measures how far each face strays, :func:`drop_unsupported` removes
the ones that stray too far, :func:`surface_fit` scores a whole mesh against the input, and
:func:`weighed_fit` adds what a renderer shows and a distance misses: the measure every rival of the pipeline is
weighed by (candidates, frames, the solid and the selection, the steps after them).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from ..shapes.io import sample_triangles
from .crossings import crossing_faces
from .defects import unorientable_faces
from .meshops import open_sides, triangle_areas, welded_in_place

SPACING_FACTOR = 3.0  # the limit is never below this many median point spacings
# The spacing the limit reads is that of this many samples of the surface, the density of the point clouds it was
# tuned on, wherever there are more.  Denser samples (a mesh input's, a dense scan's) measure a face's distance
# more finely but leave the limit as wide: their median spacing shrinks as 1/sqrt(N), and a limit narrowed with it
# fails the coarse faces of a curved result (across a capsule's caps), leaving holes a point cloud would not.
SPACING_POINTS = 8192
GRID = 6  # face samples per edge of the barycentric grid: 21 points inside each triangle
BOUND_PAD = 1e-6  # relative margin of a bounded search (``support_distance``'s ``bound``) over its bound
# A mesh's fit is weighed up by 1 + this times the share of its faces (or area) a renderer shows wrong whichever way
# they are turned (``weighed_fit``): a mesh with a tenth of its faces crossing or twisted counts as 1.4x as far.
DEFECT_WEIGHT = 4.0


def barycentric_grid(n: int) -> np.ndarray:
    """(K, 3) barycentric coordinates of a triangular grid strictly inside the triangle."""
    ij = [(i, j) for i in range(n) for j in range(n - i)]
    return np.array([[(i + 1 / 3) / n, (j + 1 / 3) / n, (n - i - j - 2 / 3) / n] for i, j in ij])


_BARY = barycentric_grid(GRID)


def face_samples(vertices: np.ndarray, faces: np.ndarray, bary: np.ndarray = _BARY) -> np.ndarray:
    """(F, K, 3) points on a barycentric grid inside each face: ``bary`` (K, 3), :func:`barycentric_grid`'s."""
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces, dtype=np.int64).reshape(-1, 3)]
    return np.einsum("kj,fjd->fkd", bary, tri)


def support_distance(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray,
                     tree: cKDTree | None = None, bound: float = np.inf) -> np.ndarray:
    """How far each face strays from the input surface.

    Parameters
    ----------
    vertices : (N, 3) float
    faces : (F, 3) int
    points : (P, 3) float
        Dense samples of the input surface, in the frame of ``vertices``.
    tree : cKDTree of ``points``, optional (built when not given)
    bound : float
        The distances up to ``bound`` are exact; a face farther than ``bound`` gets some distance above it
        (``inf`` where the nearest-point search stopped at the bound, which spares the search across empty
        space that costs most for faces far from the input).

    Returns
    -------
    (F,) float64 : the median, over a grid of points inside the face, of the distance to the
    nearest input point (same unit as the positions).
    """
    samples = face_samples(vertices, faces)
    if len(samples) == 0:
        return np.zeros(0)
    if tree is None:
        tree = cKDTree(np.asarray(points, dtype=np.float64))
    # The search keeps points strictly nearer than its bound: padded, so a distance equal to ``bound`` stays.
    reach = bound * (1.0 + BOUND_PAD) if np.isfinite(bound) else np.inf
    dist, _ = tree.query(samples.reshape(-1, 3), distance_upper_bound=reach)
    return np.median(dist.reshape(samples.shape[:2]), axis=1)


class SupportCache:
    """:func:`support_distance` of faces given as vertex triples, each triple computed once.

    Hole filling asks for the same ears and triangles again and again as it clips, repairs and
    retries (about a third of its requests repeat).  A triple is keyed in its own vertex order: the
    grid of samples inside a face depends on it, so (a, b, c) and (b, c, a) may differ slightly.

    Hole filling only compares a face's distance with its limit and ranks the faces within it, so the
    searches stop at the largest limit the cache serves (``bound``): a face beyond it reads some distance
    above it, and what is within it is exact.

    Parameters
    ----------
    vertices : (N, 3) float
    points : (P, 3) float
    tree : cKDTree of ``points``, optional
    bound : float, the largest limit the callers compare distances with (``support_distance``)
    """

    def __init__(self, vertices: np.ndarray, points: np.ndarray, tree: cKDTree | None = None,
                 bound: float = np.inf):
        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.points = np.asarray(points, dtype=np.float64)
        self.tree = tree if tree is not None else cKDTree(self.points)
        self.bound = float(bound)
        self._known: dict[tuple[int, int, int], float] = {}

    def __call__(self, faces: np.ndarray) -> np.ndarray:
        """(F,) float64: ``support_distance(vertices, faces, points)``, for (F, 3) int ``faces``."""
        keys = [tuple(t) for t in np.asarray(faces, dtype=np.int64).reshape(-1, 3).tolist()]
        new = list(dict.fromkeys(k for k in keys if k not in self._known))
        if new:
            d = support_distance(self.vertices, np.array(new, dtype=np.int64), self.points, self.tree, self.bound)
            self._known.update(zip(new, d.tolist(), strict=True))
        return np.array([self._known[k] for k in keys], dtype=np.float64)


def support_limit(points: np.ndarray, tol: float, tree: cKDTree | None = None) -> float:
    """The largest :func:`support_distance` of a face on the surface: ``tol`` times the points'
    longest side, and at least ``SPACING_FACTOR`` median point spacings, as ``SPACING_POINTS`` samples of
    the surface would be spaced where there are more.

    Parameters
    ----------
    points : (P, 3) float, at least two
    tol : float
    tree : cKDTree of ``points``, optional
    """
    pts = np.asarray(points, dtype=np.float64)
    tree = tree if tree is not None else cKDTree(pts)
    # Between sparse samples a face on the surface is itself up to about half their spacing away.
    nn, _ = tree.query(pts, k=2)
    spacing = float(np.median(nn[:, 1])) * max(1.0, math.sqrt(len(pts) / SPACING_POINTS))
    return max(tol * float((pts.max(0) - pts.min(0)).max()), SPACING_FACTOR * spacing)


def drop_unsupported(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, tol: float) -> np.ndarray:
    """The faces that lie on the input surface: ``faces[supported(...)]``; see :func:`supported`.

    Returns
    -------
    (F', 3) int64 : the kept faces, in their order.
    """
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    return faces[supported(vertices, faces, points, tol)]


def supported(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, tol: float,
              score: np.ndarray | None = None) -> np.ndarray:
    """Which faces lie on the input surface.

    A face is dropped when its :func:`support_distance` exceeds the limit: ``tol`` times the
    points' longest side, and at least ``SPACING_FACTOR`` median point spacings.  Except: a vertex
    that lies on the surface (within the limit) keeps its best-supported face when all its faces
    would go, so that a thin part joined by wrong faces is not cut off.

    Parameters
    ----------
    vertices : (N, 3) float
    faces : (F, 3) int
    points : (P, 3) float
        Dense samples of the input surface (a few thousand or more).
    tol : float
        Relative to the longest side of the points' bounding box.
    score : (F,) float, optional
        :func:`support_distance` of the faces, if already computed.

    Returns
    -------
    (F,) bool : True for the faces to keep.
    """
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    pts = np.asarray(points, dtype=np.float64)
    if len(faces) == 0 or len(pts) < 2:
        return np.ones(len(faces), dtype=bool)
    tree = cKDTree(pts)
    limit = support_limit(pts, tol, tree)
    if score is None:
        score = support_distance(vertices, faces, pts, tree)
    bad = score > limit
    if not bad.any():
        return ~bad
    # A vertex on the surface keeps its best-supported face: dropping all its faces would cut off
    # the thin part it ends (a spear tip, a leaf) instead of a wrong connection.
    dist_v, _ = tree.query(np.asarray(vertices, dtype=np.float64))
    order = np.argsort(score)  # best-supported first: each orphaned vertex meets its best face first
    kept_v = np.zeros(len(dist_v), dtype=bool)
    kept_v[faces[~bad].ravel()] = True
    for fi in order[bad[order]]:
        tri = faces[fi]
        if any(not kept_v[v] and dist_v[v] <= limit for v in tri):
            bad[fi] = False
            kept_v[tri] = True
    return ~bad


FIT_SAMPLES = 4096  # points sampled on a candidate mesh to score it against the input
# Share of the worst distance in a candidate's score: between two candidates of about the same mean
# distance, the one with the smaller hole or stray sheet (held-out packages, docs/results.md).
HAUSDORFF_WEIGHT = 0.1


def surface_fit(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, seed: int = 0,
                hausdorff_weight: float = HAUSDORFF_WEIGHT) -> float:
    """How well a mesh matches the input surface: a Chamfer distance and a share of the Hausdorff
    distance (lower is better).

    Parameters
    ----------
    vertices : (N, 3) float
    faces : (F, 3) int, at least one
    points : (P, 3) float
        Samples of the input surface, in the frame of ``vertices``.
    seed : int
        Of the area-weighted samples drawn on the mesh.
    hausdorff_weight : float
        Weight of the largest distance either way (mesh sample to input point or back).

    Returns
    -------
    float : (mean distance from mesh samples to the points + mean distance from the points to the
    mesh samples) / 2 + ``hausdorff_weight`` x the largest of all those distances, in the unit of
    the positions.  Stray surface raises the first mean, parts the mesh leaves out the second; the
    largest is the worst of either.
    """
    samples, _ = sample_triangles(np.asarray(vertices, dtype=np.float64), np.asarray(faces), FIT_SAMPLES,
                                  np.random.default_rng(seed))
    pts = np.asarray(points, dtype=np.float64)
    stray, _ = cKDTree(pts).query(samples)
    missed, _ = cKDTree(samples).query(pts)
    return float(stray.mean() + missed.mean()) / 2 + hausdorff_weight * float(max(stray.max(), missed.max()))


def hole_faces(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(F,) bool, the ``faces`` (F, 3) along an open edge (vertices welded) across which the input goes on: a hole
    or a slit, through which a renderer shows the inside or the back of the far side, not the input's own border.
    The input goes on across an edge where one of its samples (``points`` (P, 3)) lies within a support limit
    (:func:`support_limit`) of the point two limits beyond the edge's middle, in its face's plane: where the input
    stops at the edge, its last samples lie about two limits from there."""
    v, f = welded_in_place(vertices, faces)
    out = np.zeros(len(f), dtype=bool)
    open_ = np.flatnonzero(open_sides(f))
    if len(open_) == 0 or len(points) < 2:
        return out
    face, corner = open_ % len(f), open_ // len(f)
    t = v[f[face]]  # (K, 3, 3)
    a, b = t[np.arange(len(face)), corner], t[np.arange(len(face)), (corner + 1) % 3]
    c = t[np.arange(len(face)), (corner + 2) % 3]
    mid, along = (a + b) / 2, b - a
    along /= np.maximum(np.linalg.norm(along, axis=1, keepdims=True), 1e-300)
    inward = c - mid
    away = -(inward - np.einsum("kd,kd->k", inward, along)[:, None] * along)
    away /= np.maximum(np.linalg.norm(away, axis=1, keepdims=True), 1e-300)
    tree = cKDTree(np.asarray(points, dtype=np.float64))
    limit = support_limit(points, 0.0, tree)
    beyond = tree.query(mid + 2 * limit * away, distance_upper_bound=limit)[0] < np.inf
    out[face[beyond]] = True
    return out


def defect_share(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray | None = None,
                 by_area: bool = False) -> float:
    """The share of ``faces`` (F, 3), or with ``by_area`` of their area, in faces that cross another face
    (``crossings.crossing_faces``), lie along an edge no turning makes agree (``defects.unorientable_faces``: a strip
    twisted like a Moebius band) or, with the input's samples ``points``, along a hole (:func:`hole_faces`): what a
    renderer shows as a face through another, the back of a face, or the inside through a hole.

    A share of the faces grows where a mesh merges the clean faces around a defect and shows no more of it; a share
    of the area does not, and is what weighs a rival of fewer faces made from a mesh against it (``by_area``).
    Candidates and frames, which are other meshes altogether, are weighed by the share of faces: by area, a
    candidate that left out a whole part (and its crossings) weighed nearer than one that kept it crossing in a
    few large faces."""
    if len(faces) == 0:
        return 0.0
    bad = crossing_faces(vertices, faces) | unorientable_faces(vertices, faces)
    if points is not None:
        bad |= hole_faces(vertices, faces, points)
    if not by_area:
        return float(bad.mean())
    area = triangle_areas(np.asarray(vertices, dtype=np.float64), faces)
    total = float(area.sum())
    return float(area[bad].sum()) / total if total > 0 else float(bad.mean())


def weighed_fit(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, seed: int = 0,
                by_area: bool = False) -> float:
    """What a rival is weighed by (lower is better): :func:`surface_fit` times 1 + ``DEFECT_WEIGHT`` x
    :func:`defect_share`.  A distance alone prefers a sheet folded through itself, twisted where a thin part
    should be a solid, or holed where the input goes on, over the clean boundary of a solid a little farther from
    the input.

    Parameters
    ----------
    vertices : (N, 3) float
    faces : (F, 3) int, at least one
    points : (P, 3) float, samples of the input surface in the frame of ``vertices``
    seed : int, of the samples drawn on the mesh
    by_area : bool, the defects' share of the area, not of the faces (:func:`defect_share`)
    """
    share = defect_share(vertices, faces, points, by_area)
    return surface_fit(vertices, faces, points, seed) * (1.0 + DEFECT_WEIGHT * share)
