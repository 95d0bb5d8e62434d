"""Steps 4-9, the face stage: faces from the decoded vertices and the predicted edges.

:func:`mesh_from_adjacency` is the one entry: with ``TriangleConfig.selection`` = ``"surface"`` (what ships) the
surface selection of ``surface_triangles`` (candidates on the input surface, ``selection``'s bookkeeping, hole
filling in ``holes``, the closure of ``closure``), else the paper's rule of ``triangles`` (every 3-clique of the
edge graph, cleaned up); both then lose the vertices of flat regions (``simplify``).  ``support`` measures how
far faces stray from the input; ``filtering`` re-predicts edges under masks; ``pieces`` splits pinched vertices
and drops stray pieces; ``facecount`` brings a result to the face count asked for; ``meshops`` holds the small
mesh helpers all of them share.
"""

from __future__ import annotations

import numpy as np

from .cliques import as_edges, triangles_from_adjacency
from .meshops import remove_unreferenced
from .orient import orient_faces
from .simplify import collapse_flat
from .support import support_distance, supported
from .surface_triangles import surface_mesh
from .triangles import TriangleConfig, drop_coplanar_diagonals, drop_degenerate, limit_faces_per_edge


def mesh_from_adjacency(vertices: np.ndarray, adj, config: TriangleConfig | None = None,
                        points: np.ndarray | None = None, logits: np.ndarray | None = None,
                        oriented: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and a predicted adjacency -> a cleaned, oriented triangle mesh.

    Parameters
    ----------
    vertices : (N, 3) float
        Positions (any frame; tolerances are relative to the bounding box).
    adj : (N, N) array, sparse matrix or (E, 2) edge list
    config : TriangleConfig
    points : (P, 3) float, optional
        Samples of the input surface in the frame of ``vertices``: with ``config.support_tol``,
        faces that leave that surface are dropped, and ``config.max_faces_per_edge`` keeps the
        best-supported faces first.  Needed by ``config.selection == "surface"``.
    logits : (N, N) float, optional
        The model's edge logits, to score candidates with ``selection == "surface"``.
    oriented : (points (Q, 3), normals (Q, 3)), optional
        The input's samples with their normals, in the frame of ``vertices``: with ``selection == "surface"`` no
        piece of the result joins faces they ask to face opposite ways (``surface_triangles.surface_mesh``).

    Returns
    -------
    vertices : (M, 3) float64 (M = N unless ``remove_unreferenced``, or the closure of ``selection``
        "surface" added vertices)
    faces : (F, 3) int64
    """
    cfg = config or TriangleConfig()
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    if cfg.selection == "surface":
        if points is None:
            raise ValueError("selection 'surface' needs samples of the input surface (points)")
        v, f = surface_mesh(v, as_edges(adj, len(v))[0], points, cfg, logits, oriented)
        f = _flat_removed(v, f, cfg)
        return remove_unreferenced(v, f)[:2] if cfg.remove_unreferenced else (v, f)
    f = triangles_from_adjacency(adj, len(v))
    if cfg.drop_zero_area:
        f = drop_degenerate(v, f, cfg.area_tol)
    if cfg.drop_coplanar_diagonals:
        f = drop_coplanar_diagonals(v, f, cfg.coplanar_tol)
    score = None  # how far each face strays from the input surface, when the input is given
    if points is not None and (cfg.support_tol is not None or cfg.max_faces_per_edge is not None):
        score = support_distance(v, f, points)
    if cfg.support_tol is not None and score is not None:
        keep = supported(v, f, points, cfg.support_tol, score)
        f, score = f[keep], score[keep]
    if cfg.max_faces_per_edge is not None:
        f = limit_faces_per_edge(f, score if score is not None else np.zeros(len(f)), cfg.max_faces_per_edge)
    if cfg.orient:
        f = orient_faces(v, f)
    f = _flat_removed(v, f, cfg)
    if cfg.remove_unreferenced:
        v, f, _ = remove_unreferenced(v, f)
    return v, f


def _flat_removed(v: np.ndarray, f: np.ndarray, cfg: TriangleConfig) -> np.ndarray:
    """``f`` without the vertices :func:`fastmesh.faces.simplify.collapse_flat` finds flat at ``cfg.flat_tol``."""
    if cfg.flat_tol is None or len(f) == 0:
        return f
    return collapse_flat(v, f, cfg.flat_tol * float(np.ptp(v, axis=0).max()), cfg.area_tol)
