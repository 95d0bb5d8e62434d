"""Input points a result leaves out, as vertices to add before the face stage runs again.

On characters and aircraft the decoder gives a limb, a wing or an engine too few vertices: the face stage can
only span it with a few long triangles (a slab across an arm held before the body, a wing's tip cut off), and
no choice of faces among those vertices follows the surface.  The input shows where: its points far from the
result.  :func:`missed_points` picks some of them, spread farthest-first, for the pipeline to add to the
decoder's vertices and connect again (``pipeline.candidate``); it keeps the new mesh only where it lies nearer
the input.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..shapes.io import sample_triangles

# Points drawn on the mesh to measure each input point's distance to it: in the unit cube a result's surface
# is a few square units, so the draw lies about 0.01 apart and a point's distance is read to within a few
# thousandths, under the tolerance it is compared with.
MESH_SAMPLES = 65536


def missed_points(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, tol: float, count: int,
                  seed: int = 0) -> np.ndarray:
    """Up to ``count`` of the input points farther than ``tol`` from the mesh, taken farthest-first.

    Parameters
    ----------
    vertices : (N, 3) float
    faces : (F, 3) int, at least one
    points : (P, 3) float
        Samples of the input surface, in the frame of ``vertices``.
    tol : float
        A point farther than this from the mesh is missed; every point taken is also farther than this from
        the mesh's vertices and from the points taken before it.
    count : int
    seed : int
        Of the draw on the mesh (:data:`MESH_SAMPLES`).

    Returns
    -------
    (K, 3) float64, K <= count: each in turn the missed point farthest from the vertices and the points
    taken before it, so that they spread over what the mesh leaves out rather than crowd one part.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    if count <= 0 or len(pts) == 0 or len(faces) == 0:
        return np.zeros((0, 3))
    drawn, _ = sample_triangles(v, np.asarray(faces), MESH_SAMPLES, np.random.default_rng(seed))
    far = pts[cKDTree(drawn).query(pts)[0] > tol]
    if len(far) == 0:
        return np.zeros((0, 3))
    gap = cKDTree(v).query(far)[0]
    taken = []
    while len(taken) < count:
        i = int(np.argmax(gap))
        if gap[i] <= tol:
            break
        taken.append(i)
        gap = np.minimum(gap, np.linalg.norm(far - far[i], axis=1))
    return far[taken]
