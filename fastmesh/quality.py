"""What a user needs to know about one result without opening it: distance to the input and topology.

The report of every generated mesh (``GenerateResult.quality``, the job's ``result.quality``,
``fastmesh generate --json``)::

    cd, hd               Chamfer and Hausdorff distance between the result and the input, in % of the
                         input's longest bounding-box side (the formulas of the evaluation protocol,
                         5,000 samples of each, fixed seed), both measured in the input's frame
    boundary_edges       edges used by one face only (the rims of holes and open borders)
    non_manifold_edges   edges used by three or more faces
    components           pieces of the mesh, connected through shared vertices
    watertight           every edge in exactly two faces

The distances are measured in the input's frame rather than each shape in its own (as the evaluation
of reference meshes does): a result that is shifted, or smaller than its input because a part is
missing, must not look perfect.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from .io import Normalization, Shape
from .metrics import N_SAMPLES, SEED, surface_distance


def edge_face_counts(faces: np.ndarray) -> np.ndarray:
    """How many faces use each undirected edge.

    Parameters
    ----------
    faces : (F, 3) int

    Returns
    -------
    (E,) int64 : one count per distinct edge (order unspecified).
    """
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    if len(e) == 0:
        return np.zeros(0, dtype=np.int64)
    return np.unique(e, axis=0, return_counts=True)[1].astype(np.int64)


def count_components(faces: np.ndarray) -> int:
    """Pieces of a mesh: groups of faces connected through shared vertices (unreferenced vertices ignored).

    Parameters
    ----------
    faces : (F, 3) int
    """
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(f) == 0:
        return 0
    used, local = np.unique(f, return_inverse=True)
    local = local.reshape(-1, 3)
    rows = np.concatenate([local[:, 0], local[:, 1]])
    cols = np.concatenate([local[:, 1], local[:, 2]])
    graph = coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(len(used), len(used)))
    return int(connected_components(graph, directed=False)[0])


def topology(faces: np.ndarray) -> dict:
    """Boundary and non-manifold edge counts, components and watertightness of a triangle mesh.

    Parameters
    ----------
    faces : (F, 3) int

    Returns
    -------
    dict : boundary_edges, non_manifold_edges, components (int), watertight (bool).
    """
    uses = edge_face_counts(faces)
    boundary, non_manifold = int((uses == 1).sum()), int((uses > 2).sum())
    return {"boundary_edges": boundary, "non_manifold_edges": non_manifold, "components": count_components(faces),
            "watertight": bool(len(uses) > 0 and boundary == 0 and non_manifold == 0)}


def mesh_quality(vertices: np.ndarray, faces: np.ndarray, shape: Shape, seed: int = SEED) -> dict:
    """The quality report of a result against the shape it was made from.

    Parameters
    ----------
    vertices : (V, 3) float, in the input's frame and units
    faces : (F, 3) int, at least one face
    shape : Shape, the input (mesh or point cloud)
    seed : int, of the samples drawn on both

    Returns
    -------
    dict : cd, hd (float, % of the input's longest side, rounded to 0.001), then :func:`topology`'s keys.
    """
    frame = Normalization.fit(np.asarray(shape.vertices, dtype=np.float64))
    d = surface_distance((vertices, faces), (shape.vertices, shape.faces), n=N_SAMPLES, seed=seed, frame=frame)
    return {"cd": round(d.cd, 3), "hd": round(d.hd, 3), **topology(faces)}
