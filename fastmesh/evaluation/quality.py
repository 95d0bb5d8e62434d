"""What a user needs to know about one result without opening it: distance to the input and topology.

The report of every generated mesh (``GenerateResult.quality``, the job's ``result.quality``,
``fastmesh generate --json``)::

    cd, hd               Chamfer and Hausdorff distance between the result and the input, in % of the
                         input's longest bounding-box side, measured to the exact surface: 5,000 samples
                         of each measured to the other's triangles (closest point, :mod:`.exact`), so a
                         result that is the input's surface reads about 0; a point cloud's samples are
                         its points, and a result's samples are measured to the discs its points stand for
    boundary_edges       edges used by one face only (the rims of holes and open borders)
    non_manifold_edges   edges used by three or more faces
    non_manifold_vertices  vertices whose faces form more than one fan (two pieces touching at a point)
    components           pieces of the mesh, connected through shared vertices
    pieces               pieces of the mesh, connected through shared edges
    input_pieces         the input's pieces: a mesh's (vertices welded), or a point cloud's groups of points
                         within a few spacings of each other (groups of under 1 % of the points ignored)
    watertight           every edge in exactly two faces
    box_gap              the largest distance between a side of the result's axis-aligned box and the same
                         side of the input's, in % of the input's longest side
    back_face_share      of what 14 views around the result show (cameras fitted to the input's box), the
                         share that is the back of a face, 0..1 (:mod:`.visible`)
    misoriented_edges    interior edges whose two faces run them the same way (:mod:`.defects`)
    misoriented_area     the area wound against the rest of its piece, share of the result's area, 0..0.5
    self_intersections   pairs of faces sharing no vertex that cross each other
    unwelded_vertices    vertices coinciding with another vertex of a different index

The samples are drawn with a fixed seed: the same mesh against the same input always gets the same figures.

The distances are measured in the input's frame rather than each shape in its own (as the evaluation
of reference meshes does): a result that is shifted, or smaller than its input because a part is
missing, must not look perfect.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ..faces.defects import defects
from ..faces.meshops import corner_fans, edge_face_counts, piece_labels, weld
from ..shapes.shape import Normalization, Shape
from .exact import exact_distance
from .metrics import N_SAMPLES, SEED, box_gap
from .visible import visible_report

QUALITY_VIEW_SIZE = 128  # pixels a side of each of the report's 14 views: the report runs on every job


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


def count_pieces(faces: np.ndarray) -> int:
    """Pieces of a mesh: groups of faces connected through shared edges (a bow tie is two).

    Parameters
    ----------
    faces : (F, 3) int
    """
    labels = piece_labels(faces)
    return int(labels.max()) + 1 if len(labels) else 0


def non_manifold_vertices(faces: np.ndarray) -> int:
    """Vertices of (F, 3) ``faces`` whose faces do not form one fan: around a manifold vertex the faces are
    joined edge to edge into a single disc or half-disc."""
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(f) == 0:
        return 0
    vertex = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    fans = np.unique(np.c_[vertex, corner_fans(f)], axis=0)[:, 0]
    return int((np.bincount(fans) > 1).sum())


def point_pieces(points: np.ndarray, k: int = 6, reach: float = 2.5, min_share: float = 0.01) -> int:
    """Groups of points within ``reach`` times the median distance to the k-th neighbour of each other,
    not counting groups of under ``min_share`` of the points (strays).

    Parameters
    ----------
    points : (N, 3) float
    """
    from scipy.spatial import cKDTree

    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(p) <= k:
        return int(len(p) > 0)
    if np.ptp(p, axis=0).max() > 0:
        p = Normalization.fit(p).apply(p)  # squared distances of far-apart coordinates overflow the tree
    tree = cKDTree(p)
    radius = reach * float(np.median(tree.query(p, k=k + 1)[0][:, -1]))
    pairs = tree.query_pairs(radius, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs), dtype=np.int8), (pairs[:, 0], pairs[:, 1])), shape=(len(p), len(p)))
    sizes = np.bincount(connected_components(graph, directed=False)[1])
    return int((sizes >= min_share * len(p)).sum())


def input_pieces(shape: Shape, n: int = 8192, seed: int = SEED) -> int:
    """The pieces of an input: a mesh's edge-connected pieces, its vertices welded (files split them at
    seams), or :func:`point_pieces` of at most ``n`` of a point cloud's points."""
    v = np.asarray(shape.vertices, dtype=np.float64)
    if shape.faces is None:
        if len(v) > n:
            v = v[np.random.default_rng(seed).choice(len(v), size=n, replace=False)]
        return point_pieces(v)
    return count_pieces(weld(v, shape.faces)[1])


def topology(faces: np.ndarray) -> dict:
    """Boundary and non-manifold edge counts, components and watertightness of a triangle mesh.

    Parameters
    ----------
    faces : (F, 3) int

    Returns
    -------
    dict : boundary_edges, non_manifold_edges, non_manifold_vertices, components, pieces (int), watertight (bool).
    """
    uses = edge_face_counts(faces)
    boundary, non_manifold = int((uses == 1).sum()), int((uses > 2).sum())
    return {"boundary_edges": boundary, "non_manifold_edges": non_manifold,
            "non_manifold_vertices": non_manifold_vertices(faces), "components": count_components(faces),
            "pieces": count_pieces(faces), "watertight": bool(len(uses) > 0 and boundary == 0 and non_manifold == 0)}


def mesh_quality(vertices: np.ndarray, faces: np.ndarray, shape: Shape, seed: int = SEED,
                 pieces_in: int | None = None) -> dict:
    """The quality report of a result against the shape it was made from.

    Parameters
    ----------
    vertices : (V, 3) float, in the input's frame and units
    faces : (F, 3) int, at least one face
    shape : Shape, the input (mesh or point cloud)
    seed : int, of the samples drawn on both (fixed by default: the report depends on the meshes only)
    pieces_in : int, optional, ``input_pieces(shape)`` where the caller has it already

    Returns
    -------
    dict : cd, hd (float, % of the input's longest side, rounded to 0.001), then :func:`topology`'s keys,
    input_pieces (:func:`input_pieces`), box_gap (``metrics.box_gap``, rounded to 0.001), back_face_share
    (rounded to 0.0001) and ``defects.defects``' keys (misoriented_area rounded to 0.0001).
    """
    frame = Normalization.fit(np.asarray(shape.vertices, dtype=np.float64))
    d = exact_distance((vertices, faces), (shape.vertices, shape.faces), frame, n=N_SAMPLES, seed=seed,
                       b_normals=shape.normals)
    # The views and the defects are measured in the input's unit frame, as the distances are: their figures are
    # shares, counts and tolerances relative to the input's size, and coordinates near the top of float64 (1e155)
    # would overflow their squared lengths, cross products and kd-trees in the input's own units.
    unit = frame.apply(vertices)
    seen = visible_report(unit, faces, box=frame.apply(shape.vertices), size=QUALITY_VIEW_SIZE)
    bad = defects(unit, faces)
    return {"cd": round(d.cd, 3), "hd": round(d.hd, 3), **topology(faces),
            "input_pieces": input_pieces(shape) if pieces_in is None else int(pieces_in),
            "box_gap": round(box_gap(vertices, shape.vertices), 3),
            "back_face_share": round(seen["back_face_share"], 4),
            **bad, "misoriented_area": round(bad["misoriented_area"], 4)}
