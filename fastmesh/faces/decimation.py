"""Quadric decimation of a mesh input: what a user does with a dense mesh instead of retopology, and so the rival
a generated result is weighed against.

:func:`quadric_decimation` is the plain decimation (``fast-simplification``: quadric edge collapses, C++) that
``fastmesh eval`` sets beside our results.  :func:`asset_decimation` is the same decimation kept only where it
is as much an asset as a generated result must be: the face count reached, edge-manifold, consistently wound,
no more pieces than the input, closed where the result must be closed, no face without area.  The pipeline
returns it where it also lies nearer the input than the generated mesh (``pipeline.result.decimated``): on a
curved or organic dense mesh the decoder does not yet place its vertices as well as the quadrics do.
"""

from __future__ import annotations

import fast_simplification
import numpy as np

from ..shapes.shape import Normalization
from .meshops import edge_face_counts, face_sides, piece_labels, remove_unreferenced, triangle_areas, weld
from .pieces import split_pinches


def quadric_decimation(vertices: np.ndarray, faces: np.ndarray, target: int) -> tuple[np.ndarray, np.ndarray]:
    """The mesh, welded (a file's seams are not edges), decimated to about ``target`` faces; as it is where it
    has no more.

    Parameters
    ----------
    vertices : (N, 3) float
    faces : (F, 3) int
    target : int, faces wanted

    Returns
    -------
    vertices : (V, 3) float64
    faces : (G, 3) int; G may stay above ``target`` (collapses stop early at open borders and non-manifold edges)
    """
    v, f = weld(vertices, faces)
    if len(f) <= target:
        return v, f
    # In the unit cube: fast-simplification works in float32, which cannot tell apart the vertices of a
    # millimetre part placed a kilometre from the origin.
    norm = Normalization.fit(v)
    out_v, out_f = fast_simplification.simplify(norm.apply(v).astype(np.float32), f.astype(np.int32),
                                                target_reduction=1.0 - target / len(f))
    return norm.invert(out_v), out_f


def asset_decimation(vertices: np.ndarray, faces: np.ndarray, target: int, pieces: int, closed: bool,
                     tolerance: float) -> tuple[np.ndarray, np.ndarray] | None:
    """:func:`quadric_decimation` to ``target`` faces where the result is an asset, else None.

    Parameters
    ----------
    vertices : (N, 3) float
    faces : (F, 3) int
    target : int, faces wanted: reached within ``tolerance`` x ``target``
    pieces : int, edge-connected pieces allowed (the input's)
    closed : bool, the result must have no open edge
    tolerance : float

    Returns
    -------
    vertices : (V, 3) float64
    faces : (G, 3) int64: no face without area, no edge in more than two faces, each inner edge once either
        way, no surface pinched at a vertex (``pieces.split_pinches``), at most ``pieces`` pieces
    """
    v, f = quadric_decimation(vertices, faces, target)
    v = np.asarray(v, dtype=np.float64)
    f = np.asarray(f, dtype=np.int64).reshape(-1, 3)
    f = f[triangle_areas(v, f) > 0]
    if not len(f) or abs(len(f) - target) > tolerance * target:
        return None
    counts = edge_face_counts(f)
    if counts.max() > 2 or (closed and counts.min() < 2) or not _wound_alike(f):
        return None
    v, f = split_pinches(*remove_unreferenced(v, f)[:2])
    return (v, f) if piece_labels(f).max() + 1 <= pieces else None


def _wound_alike(faces: np.ndarray) -> bool:
    """Whether neighbouring faces run their shared edge in opposite directions (no directed edge twice)."""
    sides = face_sides(faces)
    return len(np.unique(sides, axis=0)) == len(sides)
