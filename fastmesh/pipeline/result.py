"""Step 8, the result: made whole, brought to the face count asked for, its quality measured, written out.

:func:`whole` makes the chosen candidate whole (pieces, pinches, far vertices) or gives back a low-poly input;
:func:`planar` rebuilds a polyhedron from its planes instead of generating, :func:`flat_faced` simplifies a mesh
made of flat faces within its own surface; :func:`finished` makes the
:class:`GenerateResult` (face count, quality report, quads, UVs, placement).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial

import numpy as np

from ..evaluation.quality import mesh_quality
from ..export.output import MeshOut, finish
from ..export.quads import EdgeEvidence
from ..faces.crossings import pull_in_uncrossed
from ..faces.decimation import COUNT_SLACK, asset_decimation, quadric_decimation, repaired_decimation
from ..faces.extent import MAX_ADDED, reach_extent
from ..faces.facecount import TOLERANCE as COUNT_TOLERANCE
from ..faces.facecount import hold_count
from ..faces.flat import simplify_flat
from ..faces.kitbash import kitbash_union
from ..faces.meshops import edge_face_counts, remove_unreferenced, triangle_areas, weld
from ..faces.orient import face_input, outward_pieces
from ..faces.pieces import drop_strays, far_limit, pull_in, split_pinches, thin_crowded_edges
from ..faces.plane_cells import plane_cells
from ..faces.redistribute import redistribute
from ..faces.refine import refine
from ..faces.support import weighed_fit
from ..faces.swap import swap_edges
from ..faces.triangles import TriangleConfig
from ..models.generate import GenerationError
from ..request import PLANAR_SAMPLES, Request
from ..shapes.open_planar import open_polyhedron
from ..shapes.orientation import outward
from ..shapes.planar import polyhedron
from ..shapes.shape import Shape
from .closing import unclosed_note
from .runtime import stage

# A low-poly mesh input of a polyhedron is given back as it is when it has at most this many times the faces
# of the polyhedron rebuilt from its planes (which has no vertex inside a face, such as a cylinder cap's centre).
LOW_POLY_SLACK = 1.25
# A result that must be closed and is open loses to the input's decimation (closed) up to this factor farther from
# the input than it: closed where the input is comes before a little closeness, as a turned frame's result is kept
# up to as much farther (``frames.FRAME_MARGIN``).
CLOSED_MARGIN = 1.1
# A mesh input of at most this many faces (welded, a surface) comes back as it is without running the networks: a
# shape that few faces describe has no cheaper mesh for them to find, and ``whole`` would keep it over one as big.
# Run through the shipped networks regardless (``benchmarks/low_poly.py``, seeds 0 and 1), low-poly inputs of 64-260
# faces came back as themselves (a cylinder of 64, an icosphere of 80, a torus of 144, a faceted egg of 156 and 260)
# after 3-9 s of networks, but a capsule of 128 (126 faces generated); a cone of 24 came back on one seed and as 22
# generated faces on the other.
FEW_FACES = 100


@dataclass
class GenerateResult:
    """A generated mesh in the input's original frame, or placed as ``origin`` and ``height`` ask.

    Attributes
    ----------
    vertices : (V, 3) float64, input units (Y-up: an ``input_up=z`` input turned so; ``up=z`` turns only the OBJ and
        PLY files)
    faces : (F, 3) int64
    tokens : int, vertex tokens generated (BOS/EOS included)
    timings : dict, seconds per stage (``request.TIMED_STAGES``: encode, vertices, enhancer, faces, filtering,
        weighing), every second of the call in one
    quality : dict, distance to the input and topology (:func:`fastmesh.evaluation.quality.mesh_quality`): cd, hd (% of
        the input's size), boundary_edges, non_manifold_edges, components, watertight; and faces, target_faces,
        target_met (faces within ``facecount.TOLERANCE`` of the target; None without one) and count_step
        (``facecount.hold_count``'s: kept, simplified or split, or decimated where the input's decimation came back;
        None without a target); quads and quad_share
        (of the polygons the OBJ and PLY files hold)
    mesh : fastmesh.export.output.MeshOut, the result as written (quads, UV layout, baked texture, placement); the
        vertices above are placed as it says
    """

    vertices: np.ndarray
    faces: np.ndarray
    tokens: int
    timings: dict[str, float] = field(default_factory=dict)
    info: dict = field(default_factory=dict)
    quality: dict = field(default_factory=dict)
    mesh: MeshOut | None = None

    def export(self, fmt: str) -> bytes:
        """The result as ``glb``, ``obj`` or ``ply`` bytes."""
        return (self.mesh or MeshOut(self.vertices, self.faces)).export(fmt)



def whole(req: Request, vertices: np.ndarray, faces: np.ndarray, uncrossed: bool = False
          ) -> tuple[np.ndarray, np.ndarray, str, int]:
    """The result made whole (``pieces``: no surface pinched at a vertex, no stray pieces beyond the input's
    ``req.pieces_in``, no vertex more than ``pieces.FAR_CELLS`` cells from the input), or the input itself where
    it is a low-poly surface with no more faces (``req.count.low_poly_input``).  ``uncrossed``: no vertex is pulled
    in where its faces would then cross others (``crossings.pull_in_uncrossed``; the solid face stage's result).
    Returns vertices, faces, where they come from ("model" or "input") and how many vertices were pulled in."""
    shape = req.shape
    if uncrossed:
        vertices, pulled = pull_in_uncrossed(vertices, faces, req.surface_points, far_limit(shape.vertices))
    else:
        vertices, pulled = pull_in(vertices, req.surface_points, far_limit(shape.vertices))
    if pulled.any():
        # Vertices pulled onto one sample made one, the faces between them (no area) dropped, before pinches are
        # split into coincident copies that must stay apart; an edge the welding crowds keeps two faces.
        vertices, faces = remove_unreferenced(*weld(vertices, faces, tol=1e-12))[:2]
        faces = thin_crowded_edges(vertices, faces)
    vertices, faces = split_pinches(vertices, faces)
    vertices, faces = remove_unreferenced(vertices, drop_strays(vertices, faces, req.pieces_in, req.surface_points))[:2]
    # In the unit cube: the areas of a shape 1e-200 across underflow to 0 in its own units.
    if not len(faces) or not triangle_areas(req.frame.norm.apply(vertices), faces).any():
        raise GenerationError("no_faces", "every face of the result collapsed onto the input surface")
    low = low_poly(shape, len(faces)) if req.count.low_poly_input else None
    return (vertices, faces, "model", int(pulled.sum())) if low is None else (*low, "input", 0)


def unsplit(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The copies of split pinches (vertices at one position) made one again, where there are any: collapses and
    splits see a vertex's every face, and none moves a vertex onto another's copy."""
    if len(np.unique(vertices, axis=0)) == len(vertices):
        return vertices, faces
    return remove_unreferenced(*weld(vertices, faces, tol=1e-12))[:2]


def low_poly(shape: Shape, faces: int) -> tuple[np.ndarray, np.ndarray] | None:
    """A mesh input, welded, its pieces stored inside out turned (``orient.outward_pieces``), when it has at most
    ``faces`` faces and is a surface (no edge in three faces): a result never has more faces than a low-poly input
    unless a count is asked for."""
    if shape.faces is None or len(shape.faces) > 4 * faces:  # too many to become few by welding: not weighed
        return None
    v, f = weld(shape.vertices, shape.faces)
    if len(f) == 0 or len(f) > faces or edge_face_counts(f).max() > 2:
        return None
    return remove_unreferenced(v, outward_pieces(v, f))[:2]


def planar(req: Request, open_: bool = False, turn: np.ndarray | None = None
           ) -> tuple[np.ndarray, np.ndarray, str] | None:
    """The closed polyhedron of a piecewise-planar input (``planar.polyhedron``: exact corners, whatever
    the pose), or with ``open_`` its open surface whose open edges lie on its bounding box in its own frame or,
    turned by ``turn`` (3, 3), in its canonical one (``open_planar.open_polyhedron``; also where the points stop
    inside the box, where the input was found open or its closed parts carry sheets of their own); in the input's
    frame, with where it comes from ("planes"); or a low-poly mesh input of the same shape, welded, where it has at most
    ``LOW_POLY_SLACK`` times the rebuild's faces ("input": a cylinder's caps keep their centres).  Planes the corners
    path cannot close or open give the cells of their arrangement (``plane_cells.plane_cells``).  A closed mesh
    input of flat parts that touch or overlap gives their union rebuilt from its planes (``kitbash.kitbash_union``;
    "planes").  None where the input is not one."""
    shape, frame = req.shape, req.frame
    with stage("faces", req.timings):
        union = kitbash_union(frame.unit, shape.faces) if shape.faces is not None and not open_ else None
        if union is not None:  # closed parts that touch or overlap: their union, rebuilt from its planes
            return frame.norm.invert(union[0]), union[1], "planes"
        if shape.faces is None and shape.normals is not None:
            points, normals = frame.unit, shape.normals
        else:
            points, normals = frame.samples(PLANAR_SAMPLES, 0)
        if not open_:  # the corners, else the cells of planes the corners cannot close (a step's overhang, legs)
            found = polyhedron(points, normals) or plane_cells(points, normals)
        else:  # open where the points stop on their box (or anywhere, where the input is open or its closed
            # parts carry sheets), in their own frame or the canonical one
            found = _framed(partial(open_polyhedron, free=not req.close), points, normals, turn)
            if found is None and req.close:  # closed parts with sheets of their own (a fin, a sign) ending in the air
                found = _framed(partial(open_polyhedron, free=True), points, normals, turn)
            if found is None and not req.close:  # a closed input's cells were weighed closed already
                found = _framed(partial(plane_cells, open_=True), points, normals, turn)
                found = found if found is not None and (edge_face_counts(found[1]) == 1).any() else None  # open
    if found is None:
        return None
    low = low_poly(shape, int(LOW_POLY_SLACK * len(found[1])))
    return (frame.norm.invert(found[0]), found[1], "planes") if low is None else (*low, "input")


def _framed(rebuild: Callable, points: np.ndarray, normals: np.ndarray, turn: np.ndarray | None
            ) -> tuple[np.ndarray, np.ndarray] | None:
    """``rebuild(points, normals)`` (an open surface whose open edges lie on the points' box) in the points' own
    frame, else turned by ``turn`` (3, 3; the canonical frame, where a turned building's floor lies on its box)
    and turned back; None where neither gives one."""
    found = rebuild(points, normals)
    if found is None and turn is not None and not np.array_equal(turn, np.eye(3)):
        found = rebuild(points @ turn.T, normals @ turn.T)
        found = None if found is None else (found[0] @ turn, found[1])
    return found


def flat_faced(req: Request) -> tuple[np.ndarray, np.ndarray, str] | None:
    """A mesh input made of flat faces simplified within a fraction of a cell of its own surface
    (``flat.simplify_flat``), in the input's frame, with where it comes from ("simplified"); None where it is not
    one, or the result must be closed and the input is not.  Its vertices are the input's, its openings and pieces
    the input's, its pieces stored inside out turned (``orient.outward_pieces``)."""
    shape = req.shape
    if shape.faces is None or (req.close and not req.sealed):
        return None
    with stage("faces", req.timings):
        found = simplify_flat(req.frame.unit, shape.faces)
    return None if found is None else (req.frame.norm.invert(found[0]), outward_pieces(*found), "simplified")


def decimated(req: Request, vertices: np.ndarray, faces: np.ndarray, config: TriangleConfig
              ) -> tuple[tuple[np.ndarray, np.ndarray] | None, dict]:
    """A mesh input decimated to the result's face count (``decimation.asset_decimation``: as much an asset as
    the result, its count within ``decimation.COUNT_SLACK``; where the plain decimation is none but lies nearer,
    it repaired by ``config``'s face stage, :func:`_repaired`) where it lies nearer the input surface than the
    result, in the input's frame; and both fits (``support.weighed_fit`` against the candidates' sample of
    ``config.support_points`` at the request's seed; empty where not weighed).  None where the input is a point
    cloud, the decimation is not an asset, or the result is nearer (or, open where it must be closed, not
    ``CLOSED_MARGIN`` farther): what comes back is never farther from a mesh input than its decimation to the same
    count that a user could use instead.  With a ``target_faces`` the result is weighed once brought to it
    (:func:`held`)."""
    shape, frame = req.shape, req.frame
    if shape.faces is None:
        return None, {}
    # A result that must be closed and is open is not the asset the decimation is (closed by asset_decimation).
    margin = CLOSED_MARGIN if req.close and (edge_face_counts(faces) == 1).any() else 1.0
    model = (frame.norm.apply(vertices), faces)
    with stage("weighing", req.timings):
        rival = asset_decimation(frame.unit, shape.faces, len(faces), req.pieces_in, req.close, COUNT_SLACK)
        if rival is None:
            rival = _repaired(req, model, margin, config)
        if rival is None:
            return None, {}
        fits = rival_fits(req, config.support_points, model=model, decimated=rival)
    return (frame.norm.invert(rival[0]), rival[1]) if fits["decimated"] < margin * fits["model"] else None, fits


def _repaired(req: Request, model: tuple[np.ndarray, np.ndarray], margin: float, config: TriangleConfig
              ) -> tuple[np.ndarray, np.ndarray] | None:
    """The mesh input's decimation to the count of ``model`` (unit-cube vertices, faces) made an asset
    (``decimation.repaired_decimation``) where, as it comes, it lies nearer the input than ``model`` by ``margin``:
    the repair takes faces away and caps holes, so one that is not nearer before it is not after (and the
    selection it runs costs a second or more on a character)."""
    frame = req.frame
    plain = quadric_decimation(frame.unit, req.shape.faces, len(model[1]))
    fits = rival_fits(req, config.support_points, model=model, plain=plain)
    if fits["plain"] >= margin * fits["model"]:
        return None
    reference = frame.surface(config.support_points, req.params.seed)
    return repaired_decimation(frame.unit, req.shape.faces, len(model[1]), req.pieces_in, req.close, COUNT_SLACK,
                               reference, replace(config, close_everywhere=req.sealed), first=plain)


def redistributed(req: Request, vertices: np.ndarray, faces: np.ndarray, factor: float, support_points: int
                  ) -> tuple[tuple[np.ndarray, np.ndarray] | None, dict]:
    """A point cloud's result with its faces spread over the input surface at its face count
    (``redistribute.redistribute``) where that lies nearer the input than the result and is as closed, in the
    input's frame; and both fits (``support.weighed_fit`` against the candidates' sample of ``support_points`` at
    the request's seed; empty where not weighed).  None where the input is a mesh (weighed against its own
    decimation instead, :func:`decimated`) or the result is nearer: the split vertices are not the artist's, so
    they come back only where the input shows the result cut across its curves."""
    if req.shape.faces is not None or len(faces) == 0:
        return None, {}
    with stage("weighing", req.timings):
        rival = spread(vertices, faces, *req.count_samples, factor=factor)
        if rival is None:
            return None, {}
        norm = req.frame.norm
        fits = rival_fits(req, support_points, model=(norm.apply(vertices), faces),
                          redistributed=(norm.apply(rival[0]), rival[1]))
    return (rival if fits["redistributed"] < fits["model"] else None), fits


def spread(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, normals: np.ndarray, factor: float
           ) -> tuple[np.ndarray, np.ndarray] | None:
    """``redistribute.redistribute`` of a result as the pipeline holds it (pinches split into copies at one
    position, ``pieces.split_pinches``): the copies made one first (collapses that saw each copy apart from the
    other would give an edge of three faces once welded) and split again after.  None where the surface would
    be worse: an edge of three faces where there was none, or open where it was closed."""
    v, f = unsplit(vertices, faces)
    rival = redistribute(v, f, points, normals, factor=factor)
    if len(rival[1]) == 0:
        return None
    now, before = edge_face_counts(rival[1]), edge_face_counts(f)
    fin = (now > 2).any() and not (before > 2).any()
    opened = (now == 1).any() and not (before == 1).any()
    return None if fin or opened else split_pinches(*rival)


def extended(req: Request, vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """The result's box brought to the input's (``extent.reach_extent``, in the input's own axes: the ones its
    engine places it by): a point cloud's outermost points, a mesh's outermost vertices.  No vertex is added
    where a face count is held, nor where that would give a result more faces than a low-poly mesh input
    (:func:`low_poly`).  Returns vertices, faces and the sides reached."""
    shape, norm = req.shape, req.frame.norm
    add = not req.count.hold and low_poly(shape, len(faces) + 2 * MAX_ADDED) is None
    with stage("weighing", req.timings):
        points = req.frame.unit if shape.faces is None else req.frame.unit[np.unique(shape.faces)]
        v, f = unsplit(vertices, faces)
        unit = norm.apply(v)
        out_v, out_f, reached = reach_extent(unit, f, points, supported=shape.faces is None, add=add)
        if len(out_v) == len(unit) and np.array_equal(out_v, unit):
            return vertices, faces, 0
        return (*split_pinches(norm.invert(out_v), out_f), reached)


def refined(req: Request, vertices: np.ndarray, faces: np.ndarray, tol: float, support_points: int
            ) -> tuple[tuple[np.ndarray, np.ndarray] | None, dict, int]:
    """A point cloud's result with its edges split where the input bends away from them (``refine.refine`` at
    ``tol`` of the unit cube, against the input's samples with their normals turned out of what they enclose)
    where that lies nearer the input than the result, in the input's frame; both fits (empty where not weighed)
    and the edges split.  None where the input is a mesh (its result is weighed against its decimation) or no
    edge is split."""
    if req.shape.faces is not None or len(faces) == 0:
        return None, {}, 0
    with stage("weighing", req.timings):
        norm = req.frame.norm
        points, normals = req.count_samples
        unit_points = norm.apply(points)
        v, f = unsplit(vertices, faces)
        unit, f, splits = refine(norm.apply(v), f, unit_points, outward(unit_points, normals), tol)
        if splits == 0:
            return None, {}, 0
        fits = rival_fits(req, support_points, model=(norm.apply(vertices), faces), refined=(unit, f))
    rival = split_pinches(norm.invert(unit), f)
    return (rival if fits["refined"] < fits["model"] else None), fits, splits


def swapped(req: Request, vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """The result's edges turned where the other diagonal of their two triangles lies nearer the input and
    neither of its triangles then crosses another face (``swap.swap_edges`` against the input's samples,
    ``uncrossed``), pinched copies made one first and split again after; and the number turned (the result as it
    was where none)."""
    with stage("weighing", req.timings):
        v, f = unsplit(vertices, faces)
        f, turned = swap_edges(v, f, *req.count_samples, uncrossed=True)
        return (*split_pinches(v, f), turned) if turned else (vertices, faces, 0)


def rival_fits(req: Request, support_points: int, by_area: bool = False, **meshes: tuple[np.ndarray, np.ndarray]
               ) -> dict[str, float]:
    """``support.weighed_fit`` of each named mesh (unit-cube vertices, faces) against the candidates' sample of
    ``support_points`` of the input at the request's seed, to 6 places: the measure a rival is weighed by (its
    defects a share of the area with ``by_area``: a rival of fewer faces made from the mesh)."""
    seed = req.params.seed
    reference = req.frame.surface(support_points, seed)
    return {name: round(weighed_fit(v, f, reference, seed, by_area), 6) for name, (v, f) in meshes.items()}


def facing(req: Request, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The result's faces with its open pieces turned to face the input (``orient.face_input``), read from the
    input's samples (``req.count_samples``) with their normals turned out of what they enclose
    (``orientation.outward``: a Quake model's inward normals too; a sheet's as given)."""
    with stage("faces", req.timings):  # in the unit cube: cross products of 1e155 coordinates overflow
        points, normals = req.count_samples
        norm = req.frame.norm
        return face_input(norm.apply(vertices), faces, norm.apply(points), outward(norm.apply(points), normals))


def held(req: Request, vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, str]:
    """The result brought to the ``target_faces`` asked for (``facecount.hold_count``), pinched vertices split
    again; and the count step taken (kept, simplified or split)."""
    with stage("faces", req.timings):
        vertices, faces = unsplit(vertices, faces)
        vertices, faces, step = hold_count(vertices, faces, req.params.target_faces, *req.count_samples)
        return (*split_pinches(vertices, faces), step)


def finished(req: Request, vertices: np.ndarray, faces: np.ndarray, tokens: int, info: dict,
             evidence: EdgeEvidence | None = None, count_step: str | None = None, note: str | None = None
             ) -> GenerateResult:
    """The result with its quality report; ``count_step``: how it was brought to the face count asked for
    (:func:`held`, or "decimated" where the input's decimation came back); ``evidence``: the face model's edges,
    which choose the quads first (``quads.pair_triangles``); ``note``: why a result that was to be closed is not
    (``closing.closed_result``).  Its quality's ``closed_decision`` (:func:`closed_decision`) claims no closed mesh
    that is not one."""
    params, timings = req.params, req.timings
    met = None
    if req.count.hold:  # the count asked for holds (``facecount``)
        met = bool(abs(len(faces) - params.target_faces) <= COUNT_TOLERANCE * params.target_faces)
    # Measuring the result, then its quads, UVs, baking and placement: timed with the faces they are made of.
    with stage("faces", timings):
        measured = mesh_quality(vertices, faces, req.shape, pieces_in=req.pieces_in)
        decision, note = closed_decision(req, measured, note)
        quality = {**measured, "faces": int(len(faces)), "closed_decision": decision,
                   "target_faces": params.target_faces, "target_met": met, "count_step": count_step}
        mesh, where, notes = finish(vertices, faces, params, source=req.shape, evidence=evidence)
    return GenerateResult(vertices=mesh.vertices, faces=mesh.faces, tokens=tokens, timings=timings,
                          info={**info, "closed_decision": req.decision, "placement": where.to_dict(),
                                "notes": ([note] if note else []) + notes},
                          quality={**quality, **mesh.counts()}, mesh=mesh)


def closed_decision(req: Request, quality: dict, note: str | None) -> tuple[str, str | None]:
    """The report's ``closed_decision`` of a result whose ``quality`` (``mesh_quality``) is measured: "not_closed"
    where the request closes it (``req.close``) and it keeps open edges or edges of three or more faces, with a note
    for people (``note``, or one made here); else "asked" (closed=true or false), "closed" or "open" (decided from
    the input)."""
    open_edges, fins = int(quality["boundary_edges"]), int(quality["non_manifold_edges"])
    if req.close and (open_edges or fins):
        return "not_closed", note or unclosed_note(req, open_edges, fins)
    return (req.reason if req.reason == "asked" else "closed" if req.close else "open"), None
