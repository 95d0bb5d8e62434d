"""The last steps of a generated result (:meth:`fastmesh.pipeline.Pipeline.steps`), after the frames: brought to a
``target_faces``, then weighed against its rivals and touched up as :class:`TriangleConfig` asks."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..faces.crossings import adds_crossings, crossing_faces
from ..faces.facecount import decimate
from ..faces.meshops import (
    distance_to_triangles,
    face_sides,
    open_sides,
    point_triangle_distance,
    remove_unreferenced,
    weld,
)
from ..faces.outline import outlined
from ..faces.pieces import split_pinches
from ..faces.thin import farther_than
from ..faces.triangles import TriangleConfig
from ..request import Request
from ..tokenizer.grid import CELL
from . import result as step8
from .closing import edge_defects
from .runtime import stage

# A result with fewer faces (its flat regions cut from their outlines, its collapses within a share of a cell) is
# kept up to this factor farther from the input (by ``support.weighed_fit``, its defects a share of the area: of the
# faces, the same defects weigh more among fewer faces) than as it was: the vertices it loses lie within a cell of
# the planes they stand for, and fewer faces where the shape does not turn is what the artist's mesh has.  On the 60
# held-out results of an earlier code (``benchmarks/outline_sweep.py``) 59 outlined results were kept within 1.1
# and 56 within 1.05 (faces per reference face 1.23 and 1.25 on average, from 1.39; their fits 1.006 and 1.003 times
# the results' on average).
FEWER_FACES_MARGIN = 1.1
# Rounds of :func:`coarsened`'s collapses, each keeping the vertices around the faces the last one folded through
# others and near the input it left; a result still folded or farther after them is not coarsened.
COARSEN_ROUNDS = 3
# A sample of the input this much farther (the unit cube) from the collapsed result than from the result is left by
# the collapses: a thin tip's few small faces weigh little in a collapse's quadric; a cell is what the grid resolves.
LEFT_TOL = CELL


def last_steps(req: Request, vertices: np.ndarray, faces: np.ndarray, info: dict, result_from: str,
               config: TriangleConfig) -> tuple[np.ndarray, np.ndarray, str, str | None]:
    """The result (``result_from`` "model", or "input": a low-poly input given back) brought to a
    ``target_faces`` (``step8.held``), then, where generated, a point cloud's result weighed against its faces
    spread over the input (``step8.redistributed``, with ``TriangleConfig.redistribute``), its edges turned
    where the input lies along the other diagonal (``step8.swapped``, with ``TriangleConfig.swap_edges``;
    ``info["edges_turned"]``), a mesh input's weighed against its decimation to its face count
    (``step8.decimated``, with ``TriangleConfig.weigh_decimation``; both fits go into ``info``), then against its
    rivals of no face count (:func:`fewer_or_nearer`), and last its box brought to the input's (``step8.extended``,
    with ``TriangleConfig.reach_extent``; ``info["extent_sides"]``): vertices, faces, where they come from ("model",
    "input" or "decimated") and the count step."""
    step = None
    if req.count.hold:
        info["faces_before_count"] = int(len(faces))
        vertices, faces, step = step8.held(req, vertices, faces)
    # The boundary of a solid is closed and free of folds by construction: the redistribution's collapses, which
    # see no faces but their own, would fold it; edge turns and splits that would make a face cross are undone.
    patched = result_from == "model" and info.get("solid_fits", {}).get("faces_from") != "solid"
    if patched and config.redistribute is not None:
        rival, fits = step8.redistributed(req, vertices, faces, config.redistribute, config.support_points)
        if fits:
            info["redistribution_fits"] = fits
        if rival is not None:
            vertices, faces = rival
    if result_from == "model" and config.swap_edges:
        vertices, faces, info["edges_turned"] = step8.swapped(req, vertices, faces)
    if result_from == "model" and config.weigh_decimation:
        rival, fits = step8.decimated(req, vertices, faces, config)
        if fits:
            info["decimation_fits"] = fits
        if rival is not None:
            vertices, faces, result_from, step = *rival, "decimated", None if step is None else "decimated"
    if result_from == "model" and not req.count.hold:
        vertices, faces = fewer_or_nearer(req, vertices, faces, info, config)
    # Last: the outlines take vertices inside flat sides and along straight edges, as the box's are.
    if result_from != "input" and config.reach_extent:
        before = vertices, faces
        vertices, faces, info["extent_sides"] = step8.extended(req, vertices, faces)
        if result_from == "model" and not patched and adds_crossings(before, (vertices, faces)):
            (vertices, faces), info["extent_sides"] = before, 0  # a vertex moved out folds the solid
    return vertices, faces, result_from, step


def fewer_or_nearer(req: Request, vertices: np.ndarray, faces: np.ndarray, info: dict, config: TriangleConfig
                    ) -> tuple[np.ndarray, np.ndarray]:
    """A generated result without a ``target_faces`` weighed in turn against the rivals ``config`` turns on, each made
    from the one kept before it: its edges split where the input bends away from them (``step8.refined``,
    ``TriangleConfig.refine``) and its flat regions cut from their outlines (:func:`outlined_flat`,
    ``TriangleConfig.outline``).  Each puts its fits in ``info`` where it was weighed and what it changed where it
    was kept (0 where not): ``edges_split``, ``flat_vertices_removed``."""
    points = config.support_points
    rivals = [(config.refine is not None, "refine_fits", "edges_split",
               lambda v, f: step8.refined(req, v, f, config.refine, points)),
              (config.outline, "outline_fits", "flat_vertices_removed", lambda v, f: outlined_flat(req, v, f, points))]
    return _weighed_in_turn(vertices, faces, info, rivals)


def coarsened_closed(req: Request, vertices: np.ndarray, faces: np.ndarray, info: dict, config: TriangleConfig
                     ) -> tuple[np.ndarray, np.ndarray]:
    """A generated result without a ``target_faces``, once closed (``closing``: it fills a hole from the faces
    around it, and coarser faces there may leave it no fill that crosses nothing), weighed against its vertices that
    stand for no turn of its shape collapsed (:func:`coarsened`, ``TriangleConfig.coarsen``; ``info``'s
    ``coarsen_fits`` where weighed, ``faces_coarsened``)."""
    points = config.support_points
    rivals = [(config.coarsen is not None, "coarsen_fits", "faces_coarsened",
               lambda v, f: coarsened(req, v, f, config.coarsen, points))]
    return _weighed_in_turn(vertices, faces, info, rivals)


def _weighed_in_turn(vertices: np.ndarray, faces: np.ndarray, info: dict, rivals: list
                     ) -> tuple[np.ndarray, np.ndarray]:
    """The mesh replaced in turn by each rival that comes back: ``rivals`` of (on, the ``info`` key of its fits, the
    key of what it changed, a function of (vertices, faces) giving (rival or None, fits, count))."""
    for on, fits_key, count_key, make in rivals:
        if not on:
            continue
        rival, fits, count = make(vertices, faces)
        if fits:
            info[fits_key] = fits
        info[count_key] = count if rival is not None else 0
        if rival is not None:
            vertices, faces = rival
    return vertices, faces


def outlined_flat(req: Request, vertices: np.ndarray, faces: np.ndarray, support_points: int
                  ) -> tuple[tuple[np.ndarray, np.ndarray] | None, dict, int]:
    """The result with its flat regions triangulated from their outlines (``outline.outlined``, in the unit cube:
    no new face crosses another or gives an edge a third face; pinched copies made one first and split again
    after) where it lies within ``FEWER_FACES_MARGIN`` of the result's ``support.weighed_fit``; both fits (empty where
    not weighed) and the vertices removed.  None where none is removed or the rival is not kept."""
    with stage("weighing", req.timings):
        norm = req.frame.norm
        v, f = step8.unsplit(vertices, faces)
        out_v, out_f, removed = outlined(norm.apply(v), f)
        if removed == 0:
            return None, {}, 0
        fits = step8.rival_fits(req, support_points, by_area=True, model=(norm.apply(vertices), faces),
                                outlined=(out_v, out_f))
    kept = fits["outlined"] <= FEWER_FACES_MARGIN * fits["model"]
    return (split_pinches(norm.invert(out_v), out_f) if kept else None), fits, removed


def coarsened(req: Request, vertices: np.ndarray, faces: np.ndarray, move: float, support_points: int
              ) -> tuple[tuple[np.ndarray, np.ndarray] | None, dict, int]:
    """The result with the vertices its shape does not need collapsed: half-edge collapses of least quadric error
    while each keeps its vertex within ``move`` (unit cube) of the planes it stands for (``facecount.decimate`` to
    no count, :func:`_collapsed`), in the unit cube, pinched copies made one first and split again after.  Kept where
    it opens and crowds no edge more than the result does and lies within ``FEWER_FACES_MARGIN`` of its
    ``support.weighed_fit``; both fits (empty where not weighed) and the faces removed.  None where none is removed or
    the rival is not kept.

    The collapses see the planes of the faces around a vertex: a curved region keeps the vertices its curvature needs
    at that distance, a region the decoder tessellated finer than its shape loses the rest."""
    with stage("weighing", req.timings):
        norm = req.frame.norm
        v, f = step8.unsplit(vertices, faces)
        unit = norm.apply(v)
        fewer = _collapsed(unit, f, move, req.frame.surface(support_points, req.params.seed))
        removed = 0 if fewer is None else len(f) - len(fewer)
        if removed == 0 or _opens_or_crowds((unit, f), (unit, fewer)):
            return None, {}, 0
        fits = step8.rival_fits(req, support_points, by_area=True, model=(norm.apply(vertices), faces),
                                coarsened=(unit, fewer))
    if fits["coarsened"] > FEWER_FACES_MARGIN * fits["model"]:
        return None, fits, removed
    return split_pinches(*remove_unreferenced(v, fewer)[:2]), fits, removed


def _collapsed(unit: np.ndarray, faces: np.ndarray, move: float, points: np.ndarray) -> np.ndarray | None:
    """``facecount.decimate``'s collapses within ``move`` of ``unit`` (N, 3) and ``faces`` (F, 3), the vertices on
    the sides of their box kept (the box stays the input's) and those on open edges (a piece's border often runs
    along another piece's unwelded copy of it: a collapse there opens a slit).  A collapse sees no faces but its
    vertex's own: where they fold a face through another, or leave an input sample (``points`` (P, 3)) more than
    ``LEFT_TOL`` farther from the mesh than it was (a thin tip cut off), they are made again with the vertices within
    ``move`` of the box of each such face kept, and those of the face nearest each such sample, up to
    ``COARSEN_ROUNDS`` times.  (G, 3) faces that cross no more than ``faces`` do and leave no sample, or None."""
    lo, hi = unit.min(0), unit.max(0)
    keep = ((unit <= lo + move) | (unit >= hi - move)).any(1)
    keep[face_sides(faces)[open_sides(faces)]] = True
    crossed_before = int(crossing_faces(unit, faces).sum())
    for _ in range(COARSEN_ROUNDS):
        fewer = decimate(unit, faces, 0, max_move=move, keep=keep)
        crossed = crossing_faces(unit, fewer)
        left = _left(unit, faces, fewer, points)
        if int(crossed.sum()) <= crossed_before and not left.any():
            return fewer
        tri = unit[fewer[crossed]]
        near = ((unit[:, None] >= tri.min(1) - move) & (unit[:, None] <= tri.max(1) + move)).all(2).any(1)
        near[faces[_nearest_faces(unit, faces, points[left])]] = True
        if not (near & ~keep).any():
            return None
        keep |= near
    return None


def _left(unit: np.ndarray, faces: np.ndarray, fewer: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(P,) bool, the ``points`` more than ``LEFT_TOL`` farther from ``fewer`` than from ``faces`` (of ``unit``);
    measured exactly only for those farther than it from ``fewer`` (``thin.farther_than``), the few it can be."""
    maybe = farther_than(points, *remove_unreferenced(unit, fewer)[:2], LEFT_TOL)
    if maybe.any():
        p = points[maybe]
        maybe[maybe] = distance_to_triangles(p, unit, fewer) > distance_to_triangles(p, unit, faces) + LEFT_TOL
    return maybe


def _nearest_faces(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, k: int = 8) -> np.ndarray:
    """(P,) the face of ``faces`` (F, 3) nearest each of ``points`` (P, 3), among the ``k`` of nearest centroid."""
    if not len(points):
        return np.zeros(0, dtype=np.int64)
    k = min(k, len(faces))
    _, cand = cKDTree(vertices[faces].mean(1)).query(points, k=k)
    cand = cand.reshape(len(points), k)
    d = point_triangle_distance(np.repeat(points, k, axis=0), vertices[faces[cand.ravel()]]).reshape(-1, k)
    return cand[np.arange(len(points)), d.argmin(1)]


def _opens_or_crowds(before: tuple[np.ndarray, np.ndarray], after: tuple[np.ndarray, np.ndarray]) -> bool:
    """Whether mesh ``after`` has more open edges or more edges of three or more faces than ``before``, both once
    welded (``closing.edge_defects``): a collapse next to a piece's coincident copy can close onto it."""
    (open_before, crowded_before), (open_after, crowded_after) = (edge_defects(weld(*m)[1]) for m in (before, after))
    return open_after > open_before or crowded_after > crowded_before
