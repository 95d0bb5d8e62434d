"""A result that must be closed (``closed=true``, or an input read as closed) made closed where its own faces allow,
and otherwise a word on why it is not: the report never claims a closed mesh that is not one.

The face stage closes the holes of the meshes it makes; a result that comes from elsewhere (a low-poly input given
back, the input's decimation, a rebuild) or whose holes the face stage could not cap stays open.  Two cheap steps
close most of those: the rims of seams that lie a fraction of a cell apart (two shells of one body, exported
unwelded) made one, then the face stage's own closure on the input surface
(``surface_triangles.surface_from_faces``).  Either is kept only where it leaves the mesh closed.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..faces.crossings import adds_crossings
from ..faces.meshops import distinct_corners, edge_face_counts, face_sides, remove_unreferenced, triangle_areas, weld
from ..faces.pieces import split_pinches
from ..faces.surface_triangles import surface_from_faces
from ..faces.triangles import TriangleConfig
from ..request import Request
from ..tokenizer.grid import CELL

# Rims of open edges within this distance of each other (the unit cube: the input's longest side 1) are one seam:
# half a cell of the decoder's grid, under which no two of a result's vertices lie apart (one vertex per cell).
SEAM_TOL = 0.5 * CELL


def edge_defects(faces: np.ndarray) -> tuple[int, int]:
    """(open edges, edges of three or more faces) of ``faces`` (F, 3), vertices as they are."""
    if len(faces) == 0:
        return 0, 0
    counts = edge_face_counts(faces)
    return int((counts == 1).sum()), int((counts > 2).sum())


def weld_seams(unit: np.ndarray, faces: np.ndarray, tol: float = SEAM_TOL) -> tuple[np.ndarray, np.ndarray]:
    """The vertices of open edges within ``tol`` of one another made one (the first of each group), faces that
    collapse or repeat dropped.

    Parameters
    ----------
    unit : (V, 3) float, in the unit cube
    faces : (F, 3) int

    Returns
    -------
    vertices : (V', 3) float64, faces : (F', 3) int64
    """
    v = np.asarray(unit, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    edges = np.sort(face_sides(f), axis=1)
    uniq, counts = np.unique(edges, axis=0, return_counts=True)
    rim = np.unique(uniq[counts == 1])
    if len(rim) < 2:
        return v, f
    pairs = cKDTree(v[rim]).query_pairs(tol, output_type="ndarray")
    if not len(pairs):
        return v, f
    graph = coo_matrix((np.ones(len(pairs)), (rim[pairs[:, 0]], rim[pairs[:, 1]])), shape=(len(v), len(v)))
    _, label = connected_components(graph, directed=False)
    _, first = np.unique(label, return_index=True)
    f = first[np.searchsorted(np.unique(label), label[f])]
    f = f[distinct_corners(f)]
    f = f[np.unique(np.sort(f, axis=1), axis=0, return_index=True)[1]]
    return remove_unreferenced(v, f)[:2]


def closed_result(req: Request, vertices: np.ndarray, faces: np.ndarray, config: TriangleConfig,
                  uncrossed: bool = False) -> tuple[np.ndarray, np.ndarray, str | None]:
    """The result closed where the request closes it (``req.close``) and it is not: its seams welded
    (:func:`weld_seams`), else its holes closed by the face stage's rules (``config``, on the input surface), the
    first that leaves every edge in two faces; as it is otherwise, with a note for people saying what stays open.

    Parameters
    ----------
    req : Request
    vertices : (V, 3) float, the input's frame
    faces : (F, 3) int
    uncrossed : bool
        A closed try is kept only where it has no more faces crossing each other than the result
        (``crossings.adds_crossings``): the solid face stage's result, free of folds, stays so.

    Returns
    -------
    vertices, faces : the result, closed or as it was
    note : str or None, why a result that was to be closed is not
    """
    if not req.close or len(faces) == 0:
        return vertices, faces, None
    # Pinches split into copies at one position (``pieces.split_pinches``) made one: they are no openings.
    v, f = remove_unreferenced(*weld(vertices, faces, tol=1e-12))[:2]
    if edge_defects(f) == (0, 0):
        return vertices, faces, None
    norm = req.frame.norm
    unit = norm.apply(v)
    welded = weld_seams(unit, f)
    tries = [welded]
    if edge_defects(welded[1]) != (0, 0):
        points = req.frame.surface(config.support_points, req.params.seed)
        cfg = replace(config, close=True, close_everywhere=True)
        tries.append(surface_from_faces(*welded, points, cfg))
    for tv, tf in tries:
        tf = np.asarray(tf, dtype=np.int64).reshape(-1, 3)
        tf = tf[triangle_areas(tv, tf) > 0]
        if len(tf) and edge_defects(tf) == (0, 0) and not (uncrossed and adds_crossings((unit, f), (tv, tf))):
            tv, tf = remove_unreferenced(tv, tf)[:2]
            return (*split_pinches(norm.invert(tv), tf), None)
    return vertices, faces, unclosed_note(req, *edge_defects(f), tried=True)


def unclosed_note(req: Request, open_edges: int, fins: int, tried: bool = False) -> str:
    """For people: a result that was to be closed keeps ``open_edges`` open edges and ``fins`` edges of three or
    more faces; ``tried``: :func:`closed_result` could not close it."""
    why = "closed=true was asked" if req.reason == "asked" else f"the input reads as closed ({req.reason})"
    parts = [f"{open_edges} open edges"] if open_edges else []
    parts += [f"{fins} edges of three or more faces"] if fins else []
    how = (": neither welding its seams (rims within half a grid cell) nor capping its holes on the input surface "
           "closed it") if tried else ""
    return f"{why}, but the result keeps {' and '.join(parts)}{how}"
