"""Quality metrics, exactly as the evaluation protocol (docs/method.md) defines them.

Chamfer and Hausdorff distances: each shape is normalised on its own (bounding-box centre
to the origin, longest side 1), 5,000 points are sampled on it (area-weighted, fixed seed),
nearest neighbours come from a KD-tree, and both numbers are in percent of the longest
side (plain L2 distances, not squared):

    CD = 100 * (mean_a min_b |a - b| + mean_b min_a |b - a|) / 2
    HD = 100 * max(max_a min_b |a - b|, max_b min_a |b - a|)

Vertex metrics compare the vertex stage's output with the artist's vertices in cells of the
7-bit grid (:func:`vertex_metrics`).

Edge metrics compare predicted and true undirected edges of the face stage.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..faces.meshops import distance_to_triangles, distinct_corners, face_sides, normalize_edges
from ..shapes.io import sample_triangles
from ..shapes.shape import Normalization
from ..tokenizer.grid import CELL  # one cell of the 7-bit grid, in units of the longest bounding-box side

N_SAMPLES = 5000
SEED = 0
MATCH_CELLS = (1, 2)  # vertex precision / recall radii, in cells
SURFACE_CELLS = 1.5  # a generated vertex farther than this from the input surface is off it


@dataclass(frozen=True)
class SurfaceDistance:
    """Chamfer and Hausdorff distance in % of the longest bounding-box side.

    ``mean_ab`` and ``mean_ba`` are the two halves of CD (mean distance from a's samples to b and
    from b's to a): with a = result and b = reference, stray surface and holes respectively.
    """

    cd: float
    hd: float
    mean_ab: float = float("nan")
    mean_ba: float = float("nan")

    def to_dict(self) -> dict:
        return {"cd": self.cd, "hd": self.hd}


def normalized_samples(vertices: np.ndarray, faces: np.ndarray | None, n: int = N_SAMPLES,
                       seed: int = SEED, frame: Normalization | None = None) -> np.ndarray:
    """Points on a shape after the EVAL normalisation (or ``frame``'s).

    Parameters
    ----------
    vertices : (V, 3) float
    faces : (F, 3) int or None
        None (or empty) for a point cloud: ``n`` of its points are drawn (all of them,
        in order, when it has ``n`` or fewer).
    n : int
        Number of samples.
    seed : int
        Seed of the sampler; the same seed gives the same points.
    frame : Normalization, optional
        Normalise with this one instead of the shape's own (to measure a shape in another's frame).

    Returns
    -------
    (n, 3) float64 points (fewer for a small point cloud), unit-longest-side frame.
    """
    frame = frame or Normalization.fit(np.asarray(vertices, dtype=np.float64))
    v = frame.apply(vertices)
    rng = np.random.default_rng(seed)
    if faces is None or len(faces) == 0:
        if len(v) <= n:
            return v
        return v[np.sort(rng.choice(len(v), size=n, replace=False))]
    pts, _ = sample_triangles(v, np.asarray(faces, dtype=np.int64), n, rng)
    return pts.astype(np.float64)


def nearest_distances(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(|A|,) distances from each point of ``a`` to ``b`` and (|B|,) from ``b`` to ``a`` (KD-trees)."""
    from scipy.spatial import cKDTree

    d_ab, _ = cKDTree(b).query(a, k=1)
    d_ba, _ = cKDTree(a).query(b, k=1)
    return d_ab, d_ba


def surface_distance(a: tuple[np.ndarray, np.ndarray | None], b: tuple[np.ndarray, np.ndarray | None],
                     n: int = N_SAMPLES, seed: int = SEED, frame: Normalization | None = None) -> SurfaceDistance:
    """Chamfer and Hausdorff distance between two shapes given as ``(vertices, faces)`` pairs.

    Both shapes are sampled with the same ``seed``; faces may be None for a point cloud.  Each is
    normalised on its own (EVAL.md), or both with ``frame`` when given: then a shift or a wrong scale
    between them counts too.
    """
    pa = normalized_samples(*a, n=n, seed=seed, frame=frame)
    pb = normalized_samples(*b, n=n, seed=seed, frame=frame)
    d_ab, d_ba = nearest_distances(pa, pb)
    cd = 100.0 * (d_ab.mean() + d_ba.mean()) / 2.0
    hd = 100.0 * max(d_ab.max(), d_ba.max())
    return SurfaceDistance(cd=float(cd), hd=float(hd), mean_ab=float(100.0 * d_ab.mean()),
                           mean_ba=float(100.0 * d_ba.mean()))


def box_gap(vertices: np.ndarray, reference: np.ndarray) -> float:
    """The largest distance between a side of the axis-aligned box of ``vertices`` (N, 3) and the same side of
    the box of ``reference`` (M, 3), in % of the reference box's longest side: how far a result's extent (its
    height, where it stands) is off its input's.  Each shape's own normalisation above scales by its own box,
    so a gap of g % moves a result's far side by about g % against its reference's."""
    v, r = np.asarray(vertices, dtype=np.float64), np.asarray(reference, dtype=np.float64)
    gaps = np.abs(np.concatenate([v.min(axis=0) - r.min(axis=0), v.max(axis=0) - r.max(axis=0)]))
    return float(100.0 * gaps.max() / max(float(np.ptp(r, axis=0).max()), 1e-300))


def chamfer(a: tuple[np.ndarray, np.ndarray | None], b: tuple[np.ndarray, np.ndarray | None],
            n: int = N_SAMPLES, seed: int = SEED) -> float:
    """Chamfer distance (% of the longest side) between ``(vertices, faces)`` pairs."""
    return surface_distance(a, b, n=n, seed=seed).cd


def hausdorff(a: tuple[np.ndarray, np.ndarray | None], b: tuple[np.ndarray, np.ndarray | None],
              n: int = N_SAMPLES, seed: int = SEED) -> float:
    """Hausdorff distance (% of the longest side) between ``(vertices, faces)`` pairs."""
    return surface_distance(a, b, n=n, seed=seed).hd


# --------------------------------------------------------------------------- vertices


def vertex_metrics(vertices: np.ndarray, reference: np.ndarray, surface_vertices: np.ndarray | None = None,
                   surface_faces: np.ndarray | None = None) -> dict:
    """How well generated vertices find the artist's, in cells of the 7-bit grid.

    Everything is given in the reference's normalised frame (``shape.Normalization.fit`` of the
    reference mesh: bounding-box centre at the origin, longest side 1), where one cell is
    ``CELL`` = 1/128.  "Within k cells" means a Euclidean distance <= k / 128.

    Parameters
    ----------
    vertices : (N, 3) float
        Generated vertices.
    reference : (M, 3) float, M >= 1
        The artist's vertices.
    surface_vertices : (S, 3) float, optional
    surface_faces : (G, 3) int, optional
        The input surface as triangles; without it ``on_surface`` is not computed.

    Returns
    -------
    dict :
        ``precision_1``, ``precision_2``: share of generated vertices within 1 and 2 cells of a
        reference vertex (0 with no generated vertex);
        ``recall_1``, ``recall_2``: share of reference vertices within 1 and 2 cells of a generated one;
        ``on_surface``: share of generated vertices within ``SURFACE_CELLS`` cells of the surface;
        ``count_ratio``: N / M; ``generated``: N; ``reference``: M.
    """
    from scipy.spatial import cKDTree

    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    ref = np.asarray(reference, dtype=np.float64).reshape(-1, 3)
    if len(ref) == 0:
        raise ValueError("vertex_metrics needs at least one reference vertex")
    out: dict = {}
    if len(v):
        d_gen, _ = cKDTree(ref).query(v)
        d_ref, _ = cKDTree(v).query(ref)
    else:
        d_gen, d_ref = np.zeros(0), np.full(len(ref), np.inf)
    for k in MATCH_CELLS:
        out[f"precision_{k}"] = float((d_gen <= k * CELL).mean()) if len(v) else 0.0
    for k in MATCH_CELLS:
        out[f"recall_{k}"] = float((d_ref <= k * CELL).mean())
    if surface_vertices is not None and surface_faces is not None:
        d_surf = distance_to_triangles(v, surface_vertices, surface_faces)
        out["on_surface"] = float((d_surf <= SURFACE_CELLS * CELL).mean()) if len(v) else 0.0
    out.update(count_ratio=len(v) / len(ref), generated=len(v), reference=len(ref))
    return out


# --------------------------------------------------------------------------- edges


def edge_metrics(pred_edges: np.ndarray, true_edges: np.ndarray) -> dict:
    """Precision, recall and F1 of predicted vs true undirected edges.

    Parameters
    ----------
    pred_edges, true_edges : (E, 2) int
        Vertex index pairs in any order and orientation; duplicates count once.

    Returns
    -------
    dict with ``precision``, ``recall``, ``f1`` (fractions in [0, 1]) and the counts
    ``tp``, ``fp``, ``fn``.  With nothing predicted precision is 0 (1 when there is also
    nothing to find); with nothing to find recall is 1.
    """
    p, t = normalize_edges(pred_edges), normalize_edges(true_edges)
    n = int(max(p.max(initial=-1), t.max(initial=-1))) + 1
    tp = int(np.isin(p[:, 0] * n + p[:, 1], t[:, 0] * n + t[:, 1]).sum())
    fp, fn = len(p) - tp, len(t) - tp
    precision = tp / len(p) if len(p) else float(len(t) == 0)
    recall = tp / len(t) if len(t) else 1.0
    f1 = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return {"precision": precision, "recall": recall, "f1": f1, "tp": tp, "fp": fp, "fn": fn}


# --------------------------------------------------------------------------- topology


def mesh_topology(vertices: np.ndarray, faces: np.ndarray, merge: bool = True) -> dict:
    """Whether a mesh is a surface, and of how many pieces.

    Parameters
    ----------
    vertices : (V, 3) float
    faces : (F, 3) int
    merge : bool
        Treat vertices at the same position as one (files split vertices at UV and normal seams).

    Returns
    -------
    dict: ``edge_manifold`` (no edge in more than two faces), ``watertight`` (every edge in exactly
    two faces, at least one face), ``pieces`` (connected parts of the faces, joined at shared
    vertices).
    """
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if merge and len(f):
        _, ids = np.unique(np.asarray(vertices, dtype=np.float64), axis=0, return_inverse=True)
        f = ids.reshape(-1)[f]
    f = f[distinct_corners(f)]
    if len(f) == 0:
        return {"edge_manifold": True, "watertight": False, "pieces": 0}
    e = np.sort(face_sides(f), axis=1)
    _, count = np.unique(e, axis=0, return_counts=True)
    used, remap = np.unique(f, return_inverse=True)
    r = remap.reshape(-1, 3)
    g = sp.coo_matrix((np.ones(2 * len(r)), (np.r_[r[:, 0], r[:, 1]], np.r_[r[:, 1], r[:, 2]])),
                      shape=(len(used), len(used)))
    return {"edge_manifold": bool(count.max() <= 2), "watertight": bool((count == 2).all()),
            "pieces": int(connected_components(g, directed=False)[0])}
