"""A dense mesh made of flat faces, simplified within a fraction of a cell of its own surface.

A hard-surface mesh tessellated finely (a CAD export, a prop remeshed or subdivided without smoothing) is a few
planes cut into many triangles; its artist mesh is those planes with a vertex only where they meet.  The mesh
itself says so exactly, with no network: nearly every edge joins two faces of one plane.  :func:`simplify_flat`
collapses its vertices one onto another (after the collapses of no error, ``facecount.decimate``: half-edges)
while each collapse keeps the surface within ``FlatConfig.max_move`` of the planes it replaces, and
keeps the result only where it lies within ``FlatConfig.max_gap`` of the input both ways.  The bound is an
area-weighted mean over those planes, so where a small curved face meets a large flat one (a boss's rim on its cap)
the surface may leave it by more: a result that strays past the gap is made again at half the bound, up to
``FlatConfig.tries`` times.  A mixed mesh (flat faces with round parts on them: a machined part, a prop with a dome
or a knob) keeps its flat faces as their outlines and its round parts within the bound; a curved mesh (a scan, a
sculpt, a smooth subdivision) has few flat edges and is left to the networks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import fast_simplification
import numpy as np
from scipy.spatial import cKDTree

from ..shapes.corners import edge_turns
from ..shapes.io import sample_surface
from ..shapes.shape import Shape
from ..tokenizer.grid import CELL
from .facecount import decimate
from .meshops import distance_to_triangles, edge_face_counts, remove_unreferenced, triangle_areas, weld


@dataclass(frozen=True)
class FlatConfig:
    """When and how far :func:`simplify_flat` simplifies, in the unit cube (the input's longest side 1).

    Attributes
    ----------
    flat_share : share of the edges of two faces that must be flat (their faces within ``flat_degrees``): the
        boxes with round parts of tests/test_mixed_meshes.py have 0.94-0.97 of them, the held-out props remeshed
        that come back within the gap 0.59-1.0, an icosphere none
    flat_degrees : float
    max_move : a collapse keeps the merged vertex within this RMS distance of the planes it stands for
    max_gap : the result and the input lie within this distance of each other, both ways
    tries : how many times the collapses are made, each at half the last bound, while the result strays past
        ``max_gap`` less than the last one did and has at most half ``max_faces``
    max_faces : the simplified mesh is kept only with at most this many faces
    max_input_faces : a larger input is not tried (the collapses run in Python: 0.2-4 s for the 17 flat ones of
        about 20,000 faces in the held-out mesh inputs, 6-9 s for a box split into a grid of 15,000, 11-21 s for
        a box with round parts split into 58,000-104,000)
    """

    flat_share: float = 0.5
    flat_degrees: float = 0.5
    max_move: float = 0.1 * CELL
    max_gap: float = 0.5 * CELL
    tries: int = 3
    max_faces: int = 2000
    max_input_faces: int = 100_000


def flat_share(vertices: np.ndarray, faces: np.ndarray, degrees: float) -> float:
    """The share of the edges of exactly two faces (``shapes.corners.edge_turns``; ``faces`` welded) whose faces'
    planes turn by at most ``degrees``, their windings read (0 without such edges)."""
    cos = edge_turns(vertices, faces)[1]
    return float((cos >= np.cos(np.radians(degrees))).mean()) if len(cos) else 0.0


def simplify_flat(vertices: np.ndarray, faces: np.ndarray, cfg: FlatConfig = FlatConfig()
                  ) -> tuple[np.ndarray, np.ndarray] | None:
    """The mesh simplified within ``cfg.max_move`` of its own planes, or None where it is not made of flat faces
    or not edge-manifold, or the result has more than ``cfg.max_faces`` faces or strays farther than
    ``cfg.max_gap`` from it (made again at half the bound, up to ``cfg.tries`` times, while that may bring it
    within).

    Parameters
    ----------
    vertices : (N, 3) float, in the unit cube
    faces : (F, 3) int, welded first (``meshops.weld``: a file's seams are not edges)

    Returns
    -------
    vertices : (V, 3) float64, on the input's surface (the lossless collapses move a vertex by float rounding)
    faces : (G, 3) int64, windings kept, no edge in more than two (an input with such edges gives None)
    """
    if not 0 < len(faces) <= cfg.max_input_faces:
        return None
    v, f = weld(vertices, faces)
    # An edge in three faces or more (fins on a plate, sheets crossing) would stay one: the networks make a
    # manifold surface of such an input.
    if edge_face_counts(f).max() > 2 or flat_share(v, f, cfg.flat_degrees) < cfg.flat_share:
        return None
    # Collapses of no error (fast-simplification's lossless mode, C++) halve a flat mesh in milliseconds; ours,
    # in Python, then go as far as the bound allows.  Where the lossless ones stray (they may, at open borders),
    # the gap below refuses the result.
    part_v, part_f = fast_simplification.simplify(v, f, lossless=True, preserve_border=True)
    part_v = np.asarray(part_v, dtype=np.float64)
    gap = math.inf
    for attempt in range(cfg.tries):
        kept = decimate(part_v, part_f, 1, max_move=cfg.max_move / 2**attempt)
        if not 0 < len(kept) <= cfg.max_faces:
            return None  # a tighter bound keeps more faces
        out_v, out_f = remove_unreferenced(part_v, kept)[:2]
        if edge_face_counts(out_f).max() > 2:
            return None
        last, gap = gap, _gap(v, f, out_v, out_f)
        if gap <= cfg.max_gap:
            return out_v, out_f
        # Not made again where the bound is not what strays (the gap did not shrink) or where half the bound would
        # pass the cap (it about doubles a curved part's faces).
        if gap >= last or 2 * len(out_f) > cfg.max_faces:
            return None
    return None


def _gap(v: np.ndarray, f: np.ndarray, out_v: np.ndarray, out_f: np.ndarray, per_face: int = 8,
         samples: int = 32768, planes: int = 16) -> float:
    """How far the result and the input lie apart: the input's vertices from the result's faces (exact), and
    points of the result's faces from the input's surface: the least distance to the planes of the
    ``planes`` input samples nearest each (one of them lies on the point's own plane, even by a crease), or
    the distance to the nearest sample where that is over four sample spacings (a tangent plane says little so
    far from its sample); the result's vertices count as such points."""
    gap = float(distance_to_triangles(v, out_v, out_f).max())
    rng = np.random.default_rng(0)
    w = rng.dirichlet(np.ones(3), size=(len(out_f), per_face))  # (G, k, 3) barycentric weights
    inside = np.vstack([out_v, np.einsum("gkj,gjd->gkd", w, out_v[out_f]).reshape(-1, 3)])
    pts, nrm = sample_surface(Shape(vertices=v, faces=f), samples, seed=0, vertices=v)
    dist, near = cKDTree(pts).query(inside, k=planes)
    across = np.abs(np.einsum("ikj,ikj->ik", inside[:, None] - pts[near], nrm[near])).min(axis=1)
    spacing = np.sqrt(triangle_areas(v, f).sum() / samples)
    return max(gap, float(np.where(dist[:, 0] <= 4 * spacing, across, dist[:, 0]).max()))
