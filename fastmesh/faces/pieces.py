"""Whole results: no surface pinched at a vertex, no stray pieces the input does not have.

The face stage and the closure can leave two fans of faces meeting at one vertex (two closed parts
touching at a point) and small islands: a triangle closed with its own back face, a sliver of a few faces
beside a thin part.  :func:`split_pinches` gives each fan a vertex of its own (the surface becomes a
manifold; the parts still touch, now as separate pieces), and :func:`drop_strays` takes out the smallest
pieces while the result has more than the input.  :func:`pull_in` moves a vertex left far from the input
(a closure's cap across a wide opening, a stray position the enhancer gave) onto it.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..shapes.shape import Normalization
from ..tokenizer.grid import CELL
from .meshops import corner_fans, distance_to_triangles, face_sides, piece_labels, triangle_areas

# A piece is a stray when it has at most this many faces or this share of the result's area, and dropping it moves
# the result at most STRAY_SPAN of its bounding-box diagonal farther from the input: it spans no more than that,
# or the input samples it is nearest to lie within that of the rest of the result (a triangle across a solid's
# inside, its corners on the walls around it).  A long thin part of a few faces, an aircraft's wing tip, stays.
STRAY_FACES = 4
STRAY_AREA = 0.005
STRAY_SPAN = 0.01
# A vertex may lie this many of the vertex grid's cells (of the input's longest side) from the nearest input
# surface sample; one farther is moved onto that sample.  The enhancer places vertices within a cell of the
# surface, and samples are about a cell apart (8,192 on a unit box), so three cells leave every sound vertex be.
FAR_CELLS = 3
# Input samples a wide stray is weighed against (``drop_strays``): every k-th, at most this many.
COVER_SAMPLES = 16384


def split_pinches(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each vertex whose faces form several fans split into one vertex per fan, at the same position.

    Parameters
    ----------
    vertices : (N, 3) float
    faces : (F, 3) int, no edge in more than two faces

    Returns
    -------
    vertices : (N + k, 3) float64, the first N as given, then one copy per extra fan
    faces : (F, 3) int64, each corner on its fan's vertex
    """
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(f) == 0:
        return v, f
    corner = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    pairs, which = np.unique(np.c_[corner, corner_fans(f)], axis=0, return_inverse=True)
    which = which.reshape(-1)
    # The first fan of each vertex keeps the vertex; every further fan gets a new one.
    first = np.r_[True, pairs[1:, 0] != pairs[:-1, 0]]
    new_id = np.where(first, pairs[:, 0], len(v) + np.cumsum(~first) - 1)
    out = new_id[which].reshape(3, -1).T
    return np.concatenate([v, v[pairs[~first, 0]]]), out


def thin_crowded_edges(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``faces`` with at most two on any edge (vertices made one can crowd an edge), and no vertex triple twice.

    The faces on crowded edges are taken largest first, each where its edges still have room: greedy, so a face
    kept is never dropped for a later one and every edge ends with at most two.

    Parameters
    ----------
    vertices : (N, 3) float
    faces : (F, 3) int

    Returns
    -------
    (G, 3) int64, the faces kept in their order
    """
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(f) == 0:
        return f
    f = f[np.sort(np.unique(np.sort(f, axis=1), axis=0, return_index=True)[1])]
    sides = np.sort(face_sides(f), axis=1)
    edges = np.unique(sides, axis=0, return_inverse=True)[1].reshape(3, -1).T  # (F, 3) edge ids of each face
    crowded = (np.bincount(edges.ravel())[edges] > 2).any(axis=1)
    if not crowded.any():
        return f
    used = np.bincount(edges[~crowded].ravel(), minlength=int(edges.max()) + 1)
    area = triangle_areas(vertices, f)
    keep = ~crowded
    candidates = np.flatnonzero(crowded)
    for i in candidates[np.argsort(-area[candidates], kind="stable")]:
        if (used[edges[i]] < 2).all():
            keep[i] = True
            used[edges[i]] += 1
    return f[keep]


def drop_strays(vertices: np.ndarray, faces: np.ndarray, keep: int, surface: np.ndarray | None = None
                ) -> np.ndarray:
    """``faces`` without their stray pieces (at most ``STRAY_FACES`` faces or ``STRAY_AREA`` of the area, and at
    most ``STRAY_SPAN`` of the size from the input once dropped), smallest first, while more than ``keep`` pieces
    remain; the largest piece always stays.

    Parameters
    ----------
    vertices : (N, 3) float
    faces : (F, 3) int
    keep : int, the pieces the input has
    surface : (M, 3) float, optional
        Samples of the input surface in the frame of ``vertices``.  Without them only a piece that spans at most
        ``STRAY_SPAN`` is a stray; with them also a wider one whose nearest samples the rest of the result
        covers within ``STRAY_SPAN`` (:func:`_covered`).

    Returns
    -------
    (F', 3) int64 faces, in their order
    """
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    labels = piece_labels(f)
    n = int(labels.max()) + 1 if len(labels) else 0
    if n <= max(keep, 1):
        return f
    norm = Normalization.fit(np.asarray(vertices, dtype=np.float64)[f.ravel()])
    v = norm.apply(vertices)  # areas of far-apart coordinates overflow
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    piece_area = np.bincount(labels, weights=area, minlength=n)
    piece_faces = np.bincount(labels, minlength=n)
    lo = np.full((n, 3), np.inf)
    hi = np.full((n, 3), -np.inf)
    for k in range(3):
        np.minimum.at(lo, labels, v[f[:, k]])
        np.maximum.at(hi, labels, v[f[:, k]])
    size = max(float(np.linalg.norm(np.ptp(v[f.ravel()], axis=0))), 1e-300)
    span = np.linalg.norm(hi - lo, axis=1) / size
    small = (piece_faces <= STRAY_FACES) | (piece_area <= STRAY_AREA * max(area.sum(), 1e-300))
    small[np.argmax(piece_area)] = False
    stray = small & (span <= STRAY_SPAN)
    if surface is not None and len(surface):
        samples = norm.apply(surface[:: max(1, len(surface) // COVER_SAMPLES)])
        for p in np.argsort(piece_area, kind="stable"):  # each weighed against what the strays before it leave
            if small[p] and not stray[p]:
                left = ~np.isin(labels, np.flatnonzero(stray))
                stray[p] = _covered(v, f[left], labels[left] == p, samples, STRAY_SPAN * size)
    order = [p for p in np.argsort(piece_area, kind="stable") if stray[p]][: n - max(keep, 1)]
    return f[~np.isin(labels, order)]


def _covered(vertices: np.ndarray, faces: np.ndarray, mine: np.ndarray, surface: np.ndarray, tol: float) -> bool:
    """Whether the input samples ``surface`` (M, 3) nearer to the faces ``faces[mine]`` than to the others lie
    within ``tol`` of the others: the result without those faces is at most ``tol`` farther from the input."""
    d_mine = distance_to_triangles(surface, vertices, faces[mine])
    rest = faces[~mine]
    # The nearest vertex of the others bounds their distance from above: a sample at least that far from these
    # faces is not theirs, so only the samples nearer to them than that are measured exactly against the others.
    bound = cKDTree(vertices[np.unique(rest)]).query(surface)[0]
    maybe = np.flatnonzero(d_mine < bound)
    d_rest = distance_to_triangles(surface[maybe], vertices, rest) if len(maybe) else np.zeros(0)
    served = d_mine[maybe] < d_rest
    return bool(not served.any() or d_rest[served].max() <= tol)


def pull_in(vertices: np.ndarray, surface: np.ndarray, limit: float) -> tuple[np.ndarray, np.ndarray]:
    """Vertices farther than ``limit`` from every surface sample moved onto the nearest sample.

    Parameters
    ----------
    vertices : (N, 3) float
    surface : (M, 3) float, samples of the input surface in the same frame
    limit : float, in the same units (``FAR_CELLS`` cells of the input's longest side in the pipeline)

    Returns
    -------
    vertices : (N, 3) float64, the connectivity unchanged
    moved : (N,) bool, the vertices moved
    """
    v = np.asarray(vertices, dtype=np.float64).copy()
    surface = np.asarray(surface, dtype=np.float64)
    if len(v) == 0 or len(surface) == 0:
        return v, np.zeros(len(v), dtype=bool)
    # Measured in the surface's unit cube: squared distances of coordinates near 1e155 would overflow to inf,
    # and the tree answers "no neighbour" (index len(surface)) for an infinite distance.
    norm = Normalization.fit(surface)
    dist, nearest = cKDTree(norm.apply(surface)).query(norm.apply(v))
    far = (dist > limit * norm.scale) & (nearest < len(surface))
    v[far] = surface[nearest[far]]
    return v, far


def far_limit(shape_vertices: np.ndarray) -> float:
    """``FAR_CELLS`` cells of the vertex grid in the units of a shape with these (N, 3) vertices."""
    return FAR_CELLS * CELL / Normalization.fit(shape_vertices).scale
