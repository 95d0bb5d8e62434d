"""A result's vertices spread where the input surface bends, at its own face count.

On organic inputs (characters, creatures) the decoder often spans a limb or a bend with a few long triangles
that cut across the curve, where an artist (and a decimated reconstruction) spends the same faces along it.
:func:`redistribute` splits the result's longest edges, each new vertex moved onto the input surface
(``facecount.split_longest``), then collapses the least quadric error back to the face count it had
(``facecount.decimate``): faces leave the flat and the straight for the curved.  Both keep a closed,
edge-manifold result so.  Collapses cannot see a thin part's tip slide into its base, and the split
vertices are not the artist's, so the pipeline keeps the redistributed mesh only where it lies nearer the
input than the result (``pipeline.result.redistributed``).
"""

from __future__ import annotations

import numpy as np

from ..shapes.shape import Normalization
from .facecount import decimate, split_longest
from .meshops import remove_unreferenced


def redistribute(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, normals: np.ndarray,
                 factor: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """The mesh's faces spread over the input surface, their number kept.

    Parameters
    ----------
    vertices : (V, 3) float
    faces : (F, 3) int, consistently wound where it is a surface
    points, normals : (P, 3) float
        Samples of the input surface and their unit normals (either sign), in the frame of ``vertices``.
    factor : float
        The longest edges are split until the mesh has ``factor * F`` faces, then it is simplified to ``F``.

    Returns
    -------
    vertices : (V', 3) float64, the ones kept of the mesh's and of the splits'
    faces : (F', 3) int64, F' <= F (fewer only where no collapse keeps the surface a surface)
    """
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(f) == 0:
        return v, f
    # The unit cube of the result: the kd-tree's squared distances stay far from overflow (``facecount``).
    norm = Normalization.fit(v)
    surface = (norm.apply(np.asarray(points, dtype=np.float64)), np.asarray(normals, dtype=np.float64))
    unit, more = split_longest(norm.apply(v), f, int(round(factor * len(f))), surface)
    unit, fewer = remove_unreferenced(unit, decimate(unit, more, len(f)))[:2]
    return norm.invert(unit), fewer
