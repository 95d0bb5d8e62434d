"""The two-stage FastMesh pipeline: load the networks once, then ``generate`` many times.

The stages as :meth:`Pipeline.generate` runs them (``STAGES`` names their timings and progress):

    shape ──normalise──► surface samples                                      encode
          ──► vertex decoder: tokens → 7-bit cells, K candidates in one batch vertices
          then, per candidate (every candidate's enhancer before any face model):
          ──► fidelity enhancer: continuous positions inside each cell,       enhancer
              then fitted to the input's planes, those fitted onto one
              point merged (``fitting``)
          ──► face model: edge logits of all pairs in one pass                faces
          ──► prediction filtering: masked re-predictions (optional)          filtering
          ──► triangles on the input surface: candidates that lie on it,      faces
              chosen by the edge logits, kept a surface, holes closed, the
              vertices of flat regions removed (``faces.mesh_from_adjacency``,
              ``surface_triangles``, ``simplify``)
          ──► the candidate nearest the input surface (``support.surface_fit``) filtering
          ──► back to the input's frame
          ──► with target_faces: brought to that count (``facecount``)     faces

This is the Python API the CLI, the worker and the evaluation call::

    pipe = Pipeline.from_pretrained()              # shipped weights, CPU or CUDA
    result = pipe.generate(load_shape("chair.ply"), GenerateParams(seed=1))
    open("chair.glb", "wb").write(result.export("glb"))

``generate`` runs :meth:`Pipeline.steps`, the same stages as a generator that hands its vertex decoding to the
caller; ``generate_batch`` (and a worker with ``FASTMESH_MAX_BATCH`` > 1) runs several jobs' steps together and
decodes their candidates as one batch (:mod:`fastmesh.batch`).
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Generator, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from .batch import DecodeRequest
from .evaluation.quality import mesh_quality
from .export.output import MeshOut, finish
from .export.quads import EdgeEvidence
from .faces import mesh_from_adjacency
from .faces.closure import decide_closed
from .faces.facecount import TOLERANCE as COUNT_TOLERANCE
from .faces.facecount import CountRule, count_rule, hold_count
from .faces.filtering import FilterConfig, Predictor, predict_edges
from .faces.meshops import edge_face_counts, remove_unreferenced, triangle_areas, weld
from .faces.pieces import drop_strays, far_limit, pull_in, split_pinches, thin_crowded_edges
from .faces.support import surface_fit
from .faces.triangles import TriangleConfig
from .fitting import FitConfig, distinct, fit_radius, fit_samples, fit_to_planes
from .models.cells import snap_to_cells
from .models.checkpoint import load_model, save_model
from .models.encoder import EncoderConfig
from .models.generate import Cancelled, GenerationError
from .models.onnx_decode import choose_decoder
from .params import GenerateParams
from .progress import STAGES
from .request import PLANAR_SAMPLES, Frame, Request
from .shapes.canonical import canonical_rotation, frame_normals, turned_degrees
from .shapes.planar import polyhedron
from .shapes.shape import Shape
from .tokenizer import dequantize
from .tokenizer import vertex as vt
from .tokenizer.grid import CELL

__all__ = ["STAGES", "Cancelled", "GenerateParams", "GenerateResult", "GenerationError", "Pipeline",
           "default_weights_dir"]

NETWORKS = ("vertex", "enhancer", "face")
CELL_NET_DIR = "cells"  # weights folder of the cell network (models.cells.CellNet), for decoders that read it
CELL_SEED = 0  # of the input sample the cell evidence reads
# A result made in the canonical frame (``canonical``) is kept unless its surface_fit exceeds the input frame's
# by more than this factor.
FRAME_MARGIN = 1.1
# torch CPU threads when neither the caller nor $FASTMESH_TORCH_THREADS says: decoding one sequence is a chain of
# small matrix-vector products, and on our 2-core machine a second thread made generation slower, not faster.
CPU_THREADS = 1
# Threads of the stages that run with fewer than the pipeline's own count (``Pipeline.threads``): the vertex
# decoder's step is too small to share (on 16 cores, 16 threads made the vertex stage 5x slower than 1), while
# the cell network and the face stage read thousands of points at once.  benchmarks/threads.py times each stage.
STAGE_THREADS = {"vertices": 1}
# A low-poly mesh input of a polyhedron is given back as it is when it has at most this many times the faces
# of the polyhedron rebuilt from its planes (which has no vertex inside a face, such as a cylinder cap's centre).
LOW_POLY_SLACK = 1.25


def default_weights_dir() -> Path:
    """The weights shipped inside the package (``fastmesh/weights``), or ``$FASTMESH_WEIGHTS``."""
    env = os.environ.get("FASTMESH_WEIGHTS")
    return Path(env) if env else Path(__file__).parent / "weights"


@contextmanager
def stage(name: str, timings: dict[str, float]) -> Iterator[None]:
    """Time the block into ``timings[name]`` (seconds add up over candidates and frames)."""
    t = time.perf_counter()
    try:
        yield
    finally:
        timings[name] += time.perf_counter() - t


def _check(should_cancel: Callable[[], bool] | None) -> None:
    if should_cancel is not None and should_cancel():
        raise Cancelled("generation cancelled")


def _timed(predict: Predictor, timings: dict[str, float], report: Callable[[float], None], should_cancel,
           n_passes: int) -> Predictor:
    """``predict`` timed as the stages count it: its first (unmasked) pass is the face stage, each masked
    re-prediction is filtering, whose progress (the share of its passes done) it reports; cancellation is
    checked before each pass."""
    calls = 0

    def timed(order: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
        nonlocal calls
        _check(should_cancel)
        with stage("faces" if calls == 0 else "filtering", timings):
            out = predict(order, mask)
        calls += 1
        if calls > 1:
            report((calls - 1) / max(1, n_passes - 1))
        return out

    return timed


def _whole(req: Request, vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, str, int]:
    """The result made whole (``pieces``: no surface pinched at a vertex, no stray pieces beyond the input's
    ``req.pieces_in``, no vertex more than ``pieces.FAR_CELLS`` cells from the input), or the input itself where
    it is a low-poly surface with no more faces (``req.count.low_poly_input``).  Returns vertices, faces, where
    they come from ("model" or "input") and how many vertices were pulled in to the input."""
    shape = req.shape
    vertices, pulled = pull_in(vertices, req.surface_points, far_limit(shape.vertices))
    if pulled.any():
        # Vertices pulled onto one sample made one, the faces between them (no area) dropped, before pinches are
        # split into coincident copies that must stay apart; an edge the welding crowds keeps two faces.
        vertices, faces = remove_unreferenced(*weld(vertices, faces, tol=1e-12))[:2]
        faces = thin_crowded_edges(vertices, faces)
    vertices, faces = split_pinches(vertices, faces)
    vertices, faces = remove_unreferenced(vertices, drop_strays(vertices, faces, req.pieces_in))[:2]
    # In the unit cube: the areas of a shape 1e-200 across underflow to 0 in its own units.
    if not len(faces) or not triangle_areas(req.frame.norm.apply(vertices), faces).any():
        raise GenerationError("no_faces", "every face of the result collapsed onto the input surface")
    low = _low_poly(shape, len(faces)) if req.count.low_poly_input else None
    return (vertices, faces, "model", int(pulled.sum())) if low is None else (*low, "input", 0)


def _unsplit(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The copies of split pinches (vertices at one position) made one again, where there are any: collapses and
    splits see a vertex's every face, and none moves a vertex onto another's copy."""
    if len(np.unique(vertices, axis=0)) == len(vertices):
        return vertices, faces
    return remove_unreferenced(*weld(vertices, faces, tol=1e-12))[:2]


def _low_poly(shape: Shape, faces: int) -> tuple[np.ndarray, np.ndarray] | None:
    """A mesh input, welded, when it has at most ``faces`` faces and is a surface (no edge in three faces):
    a result never has more faces than a low-poly input unless a count is asked for."""
    if shape.faces is None or len(shape.faces) > 4 * faces:  # too many to become few by welding: not weighed
        return None
    v, f = weld(shape.vertices, shape.faces)
    if len(f) == 0 or len(f) > faces or edge_face_counts(f).max() > 2:
        return None
    return remove_unreferenced(v, f)[:2]


@dataclass
class GenerateResult:
    """A generated mesh in the input's original frame, or placed as ``origin`` and ``height`` ask.

    Attributes
    ----------
    vertices : (V, 3) float64, input units (Y-up; ``up=z`` turns only the OBJ and PLY files)
    faces : (F, 3) int64
    tokens : int, vertex tokens generated (BOS/EOS included)
    timings : dict, seconds per stage: encode, vertices, enhancer, faces, filtering
    quality : dict, distance to the input and topology (:func:`fastmesh.evaluation.quality.mesh_quality`): cd, hd (% of
        the input's size), boundary_edges, non_manifold_edges, components, watertight; and faces, target_faces,
        target_met (faces within ``facecount.TOLERANCE`` of the target; None without one) and count_step
        (``facecount.hold_count``'s: kept, simplified or split; None without a target); quads and quad_share
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


def choose_threads(device: torch.device, threads: int | None = None) -> int | None:
    """torch's thread count for generation: ``threads``, else ``$FASTMESH_TORCH_THREADS``, else
    :data:`CPU_THREADS` on a CPU device; None (torch's default) on a GPU."""
    if threads is None:
        env = os.environ.get("FASTMESH_TORCH_THREADS", "").strip()
        if env:
            try:
                threads = int(env)
            except ValueError:
                raise ValueError(f"FASTMESH_TORCH_THREADS must be a whole number, got {env!r}") from None
    if threads is None and device.type == "cpu":
        threads = CPU_THREADS
    if threads is not None and threads < 1:
        raise ValueError(f"torch threads must be at least 1, got {threads}")
    return threads


def auto_device(device: str | None = None) -> torch.device:
    if device:
        return torch.device(device)
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


class Pipeline:
    """The three networks plus the fixed geometry around them."""

    def __init__(self, vertex, enhancer, face, device: torch.device | str = "cpu",
                 filter_config: FilterConfig | None = None, triangle_config: TriangleConfig | None = None,
                 source: str = "", threads: int | None = None, cell_net=None,
                 fit_config: FitConfig | None = None):
        self.device = torch.device(device)
        # Process-wide (torch has one thread pool), and before the decoder is built: its ONNX session
        # takes torch's count.  See choose_threads.
        self.threads = choose_threads(self.device, threads)
        self.stage_threads = dict(STAGE_THREADS)
        if self.threads is not None:
            torch.set_num_threads(self.threads)
        if vertex.cfg.evidence_cells and cell_net is None:
            raise ValueError("this vertex decoder reads the cell network's log-odds: pass `cell_net`")
        self.cell_net = cell_net.to(self.device).eval() if cell_net is not None else None
        self.vertex = vertex.to(self.device).eval()
        self.enhancer = enhancer.to(self.device).eval()
        self.face = face.to(self.device).eval()
        self.filter_config = filter_config or FilterConfig()
        # Keep every vertex the decoder produced until the mesh is built, then drop the unused.
        self.triangle_config = triangle_config or TriangleConfig(remove_unreferenced=True)
        self.fit_config = fit_config or FitConfig()
        self.source = source
        self.max_vertices = int(vertex.cfg.max_vertices)
        # Decode steps run in ONNX Runtime on CPU when it is installed (~3x faster per token than
        # eager), with static shapes and a captured graph on CUDA; FASTMESH_DECODER=torch|onnx|static forces a
        # backend.  A snapshot of the vertex weights.
        self.decoder = choose_decoder(self.vertex, self.device, threads=self._stage_threads("vertices"))

    # ------------------------------------------------------------------ construction

    def _stage_threads(self, name: str) -> int | None:
        """torch threads of stage ``name`` (None: torch's own count, on a GPU)."""
        return None if self.threads is None else min(self.threads, self.stage_threads.get(name, self.threads))

    @contextmanager
    def threads_for(self, name: str) -> Iterator[None]:
        """Run the block with stage ``name``'s torch threads (``STAGE_THREADS``), then the pipeline's again."""
        n, before = self._stage_threads(name), torch.get_num_threads()
        if n is None or n == before:
            yield
            return
        torch.set_num_threads(n)
        try:
            yield
        finally:
            torch.set_num_threads(before)

    @classmethod
    def from_pretrained(cls, weights: str | os.PathLike | None = None, device: str | None = None,
                        threads: int | None = None) -> Pipeline:
        """Load ``vertex/``, ``enhancer/`` and ``face/`` from ``weights`` (default: the shipped ones).

        ``threads``: torch CPU threads (default ``$FASTMESH_TORCH_THREADS``, else 1 on CPU: the fastest
        measured for generating one mesh at a time); it applies to the whole process, except for the stages of
        ``STAGE_THREADS`` (the vertex decoder runs on one).
        """
        root = Path(weights) if weights else default_weights_dir()
        missing = [n for n in NETWORKS if not (root / n / "model.safetensors").exists()]
        if missing:
            raise FileNotFoundError(f"weights folder {root} lacks {', '.join(missing)} "
                                    "(each needs model.safetensors + config.json)")
        dev = auto_device(device)
        nets = {n: load_model(root / n, device=dev)[0] for n in NETWORKS}
        cell_net = (load_model(root / CELL_NET_DIR, device=dev)[0]
                    if (root / CELL_NET_DIR / "model.safetensors").exists() else None)
        settings = root / "pipeline.json"
        extra = json.loads(settings.read_text()) if settings.exists() else {}
        fcfg = FilterConfig(**extra.get("filtering", {}))
        triangle_cfg = TriangleConfig(**{"remove_unreferenced": True, **extra.get("faces", {})})
        return cls(nets["vertex"], nets["enhancer"], nets["face"], device=dev, filter_config=fcfg,
                   triangle_config=triangle_cfg, source=str(root), threads=threads, cell_net=cell_net,
                   fit_config=FitConfig(**extra.get("fit", {})))

    @classmethod
    def random(cls, size: str = "tiny", seed: int = 0, device: str | None = None,
               threads: int | None = None) -> Pipeline:
        """Randomly initialised networks, for tests and benchmarks of the machinery.

        ``tiny`` networks are a few thousand parameters.  A random face model would
        predict no edges; its output bias is set so every pair connects, which gives a
        (meaningless) mesh on every input, so the service can be tested end to end.
        Keep ``max_vertices`` small with it: N vertices make N^3/6 triangles.
        """
        from .models.enhancer import Enhancer, EnhancerConfig
        from .models.face import FaceModel, FaceModelConfig
        from .models.vertex import VertexConfig, VertexDecoder

        if size != "tiny":
            raise ValueError("only size='tiny' is defined")
        torch.manual_seed(seed)
        enc = EncoderConfig(n_points=256, n_latents=8, dim=32, depth=1, heads=2, n_freqs=4)
        vertex = VertexDecoder(VertexConfig(dim=32, depth=2, heads=2, encoder=enc, max_vertices=64, evidence=True,
                                            count_condition=True))
        enhancer = Enhancer(EnhancerConfig(dim=32, depth=1, heads=2, encoder=enc))
        face = FaceModel(FaceModelConfig(dim=32, depth=1, heads=2, edge_heads=4, edge_mlp_hidden=4, encoder=enc))
        with torch.no_grad():
            face.edge_out.bias.fill_(8.0)
        return cls(vertex, enhancer, face, device=auto_device(device), source=f"random:{size}:{seed}",
                   threads=threads)

    def save(self, directory: str | os.PathLike) -> None:
        """Write the three networks (and the filtering and clean-up settings) so ``from_pretrained`` can load them."""
        root = Path(directory)
        for name, net in zip(NETWORKS, (self.vertex, self.enhancer, self.face), strict=True):
            save_model(net, name, root / name)
        if self.cell_net is not None:
            save_model(self.cell_net, CELL_NET_DIR, root / CELL_NET_DIR)
        settings = {"filtering": asdict(self.filter_config), "faces": asdict(self.triangle_config),
                    "fit": asdict(self.fit_config)}
        (root / "pipeline.json").write_text(json.dumps(settings, indent=2))

    def info(self) -> dict:
        return {"source": self.source, "device": str(self.device), "threads": torch.get_num_threads(),
                "max_vertices": self.max_vertices,
                "decoder": getattr(self.decoder, "backend", "torch"),
                "parameters": {n: sum(p.numel() for p in net.parameters())
                               for n, net in zip(NETWORKS, (self.vertex, self.enhancer, self.face), strict=True)}}

    # ------------------------------------------------------------------ generation

    def _n_points(self) -> int:
        return max(net.cfg.encoder.n_points for net in (self.vertex, self.enhancer, self.face))

    def generate(self, shape: Shape, params: GenerateParams | None = None,
                 progress: Callable[[str, float], None] | None = None,
                 should_cancel: Callable[[], bool] | None = None) -> GenerateResult:
        """Turn a shape into an artist-style mesh in the shape's own frame.

        With ``params.candidates`` = K > 1 (and a temperature above 0) the meshes of seeds ``seed``
        ... ``seed + K - 1`` are made (their vertex tokens decoded together, as one batch) and the
        one closest to the input surface is returned
        (:func:`fastmesh.faces.support.surface_fit`): a sampled mesh sometimes leaves out a part or fills
        a flat region with vertices, and the input tells which.

        Parameters
        ----------
        shape : Shape
            Mesh or point cloud, as from ``io.load_shape``.
        params : GenerateParams
        progress : callable, optional
            ``progress(stage, fraction)``: the stage running and the overall fraction done (0..1), called
            often while the decoder runs.  Both go one way (:mod:`fastmesh.progress`): the fraction never
            decreases, the stage never returns to one passed, and filtering is named only when it runs.
        should_cancel : callable, optional
            Polled during decoding and between stages; returning True raises :class:`Cancelled`.

        Raises
        ------
        ValueError for bad parameters, :class:`GenerationError` when no mesh comes out,
        :class:`Cancelled`.
        """
        out = self.generate_batch([shape], [params], [progress], [should_cancel])[0]
        if isinstance(out, BaseException):
            raise out
        return out

    def generate_batch(self, shapes: list[Shape], params: list[GenerateParams | None],
                       progress: list[Callable[[str, float], None] | None] | None = None,
                       should_cancel: list[Callable[[], bool] | None] | None = None
                       ) -> list[GenerateResult | Exception]:
        """Several jobs at once, their vertex tokens decoded together (:mod:`fastmesh.batch`).

        Job i gives exactly what ``generate(shapes[i], params[i])`` gives alone (its candidates keep their
        seeds, evidence and sampling); jobs of different sampling settings share the rounds but not the decoder
        batch.  ``progress[i]`` and ``should_cancel[i]`` are job i's, as :meth:`generate` takes them: a cancelled
        job stops, the others go on.

        Returns
        -------
        list, per job: its :class:`GenerateResult`, or the exception it raised (``ValueError``,
        :class:`GenerationError`, :class:`Cancelled`, ...), which :meth:`generate` would raise.
        """
        from .batch import Batch

        n = len(shapes)
        if len(params) != n or (progress is not None and len(progress) != n) or (
                should_cancel is not None and len(should_cancel) != n):
            raise ValueError(f"generate_batch: {n} shapes need as many params, progress and should_cancel")
        batch = Batch(self)
        for i, shape in enumerate(shapes):
            batch.add(i, self.steps(shape, params[i], progress[i] if progress else None,
                                    should_cancel[i] if should_cancel else None))
        while len(batch):
            batch.round()
        done = batch.pop_done()
        return [done[i] for i in range(n)]

    def steps(self, shape: Shape, params: GenerateParams | None = None,
              progress: Callable[[str, float], None] | None = None, should_cancel: Callable[[], bool] | None = None
              ) -> Generator[DecodeRequest, list[torch.Tensor], GenerateResult]:
        """:meth:`generate` as a generator that stops where it needs the vertex decoder: it yields a
        :class:`fastmesh.batch.DecodeRequest` (one per frame) and is sent that request's token sequences (one
        per candidate); it returns the result.  :class:`fastmesh.batch.Batch` runs several at once."""
        params = params or GenerateParams()
        params.validate(limit=self.max_vertices)
        self._target(params)  # refuses a target_faces this decoder cannot read, before any work
        req = Request.start(shape, params, progress, should_cancel)
        # A point cloud that bounds a polyhedron is closed: the winding numbers are read only where it does not.
        cheap = shape.faces is not None or params.closed != "auto"
        if cheap:
            req.close, req.reason = decide_closed(shape, params.closed)
        flat = self._planar(req) if req.close else None
        if flat is not None:
            req.report.done("faces")
            return self._result(req, *flat[:2], tokens=0, info={"turned_degrees": 0.0, "result_from": flat[2]})
        if not cheap:
            req.close, req.reason = decide_closed(shape, params.closed)
        # The input's own frame, and its canonical one where that lays more of its walls along the axes
        # (``canonical``): each is generated, and the mesh nearer the input kept.
        frames = [np.eye(3)]
        turn = canonical_rotation(shape.vertices, frame_normals(shape))
        if not np.array_equal(turn, frames[0]):
            frames.append(turn)
        made, errors = yield from self._in_frames(req, frames)
        if not made:
            raise errors[0]
        best = self._nearest_frame(req, made)
        vertices, faces, result_from, pulled = _whole(req, best["vertices"], best["faces"])
        result = self._result(req, vertices, faces, tokens=best["tokens"],
                              info={**best["info"], "turned_degrees": round(turned_degrees(best["rotation"]), 3),
                                    "result_from": result_from, "pulled_in": pulled},
                              evidence=best["evidence"] if result_from == "model" else None)
        req.report.done()
        return result

    @staticmethod
    def _result(req: Request, vertices: np.ndarray, faces: np.ndarray, tokens: int, info: dict,
                evidence: EdgeEvidence | None = None) -> GenerateResult:
        """The result with its quality report, brought to the face count asked for (``req.count.hold``);
        ``evidence``: the face model's edges, which choose the quads first (``quads.pair_triangles``)."""
        params, timings = req.params, req.timings
        step, met = None, None
        if req.count.hold:  # the count asked for holds (``facecount``)
            info = {**info, "model_faces": int(len(faces))}
            with stage("faces", timings):
                vertices, faces = _unsplit(vertices, faces)
                vertices, faces, step = hold_count(vertices, faces, params.target_faces, *req.count_samples)
                vertices, faces = split_pinches(vertices, faces)
            met = bool(abs(len(faces) - params.target_faces) <= COUNT_TOLERANCE * params.target_faces)
        why = req.reason
        quality = {**mesh_quality(vertices, faces, req.shape, pieces_in=req.pieces_in), "faces": int(len(faces)),
                   "closed_decision": why if why == "asked" else ("closed" if req.close else "open"),
                   "target_faces": params.target_faces, "target_met": met, "count_step": step}
        # Quads, UVs, baking and placement: timed with the faces they are made of.
        with stage("faces", timings):
            mesh, where, notes = finish(vertices, faces, params, source=req.shape, evidence=evidence)
        return GenerateResult(vertices=mesh.vertices, faces=mesh.faces, tokens=tokens, timings=timings,
                              info={**info, "closed_decision": req.decision, "placement": where.to_dict(),
                                    "notes": notes},
                              quality={**quality, **mesh.counts()}, mesh=mesh)

    def _planar(self, req: Request) -> tuple[np.ndarray, np.ndarray, str] | None:
        """The closed polyhedron of a piecewise-planar input (``planar.polyhedron``: exact corners, whatever
        the pose), in the input's frame, with where it comes from ("planes"); or a low-poly mesh input of the
        same shape, welded, where it has at most ``LOW_POLY_SLACK`` times the polyhedron's faces ("input": a
        cylinder's caps keep their centres).  None where the input is not a polyhedron or a face count is asked
        for (``req.count.rebuild_planes``: the polyhedron has the count it has)."""
        if not req.count.rebuild_planes:
            return None
        shape, frame = req.shape, req.frame
        with stage("faces", req.timings):
            if shape.faces is None and shape.normals is not None:
                points, normals = frame.unit, shape.normals
            else:
                points, normals = frame.samples(PLANAR_SAMPLES, 0)
            found = polyhedron(points, normals)
        if found is None:
            return None
        low = _low_poly(shape, int(LOW_POLY_SLACK * len(found[1])))
        return (frame.norm.invert(found[0]), found[1], "planes") if low is None else (*low, "input")

    def _nearest_frame(self, req: Request, made: list[dict]) -> dict:
        """Of the results ``made`` in the input's frame and (last) in its canonical one, the canonical one
        unless its surface_fit exceeds the other's by more than ``FRAME_MARGIN``: on a box both lie on its
        planes, but the turned one has its eight corners where the input's frame has a staircase of vertices
        along each wall."""
        if len(made) == 1:
            return made[0]
        seed = req.params.seed
        with stage("filtering", req.timings):
            reference = req.frame.surface(self.triangle_config.support_points, seed)
            fits = [surface_fit(req.frame.norm.apply(m["vertices"]), m["faces"], reference, seed) for m in made]
        return made[-1] if fits[-1] <= FRAME_MARGIN * fits[0] else made[0]

    def _in_frames(self, req: Request, rotations: list[np.ndarray]
                   ) -> Generator[DecodeRequest, list[torch.Tensor], tuple[list[dict], list[GenerationError]]]:
        """The best of the candidates made with the input turned by each of ``rotations`` ((3, 3) each), turned
        back: per frame that made a mesh a dict of vertices (input frame), faces, tokens, info and rotation;
        and the errors of the frames that made none.

        Stage by stage over every frame and candidate (all encoded, all decoded, every enhancer, then the face
        stage), so that the progress passes each stage once; each frame's candidate k is still exactly what
        seed + k gives alone in that frame.  A :meth:`steps` generator: it yields each frame's decoding.
        """
        report = req.report
        frames = []
        for i, rotation in enumerate(rotations):
            report("encode", 0.0, i, len(rotations))
            frames.append(self._frame(req, rotation))
        decoded = yield from self._decode(req, frames, report.part("vertices", 0, 1))
        for frame in frames:
            frame.decoded, decoded = decoded[:len(frame.encoded)], decoded[len(frame.encoded):]
        work = [(frame, k) for frame in frames for k in range(len(frame.decoded))]
        for j, (frame, k) in enumerate(work):
            report("enhancer", 0.0, j, len(work))
            frame.positions.append(self._positions(req, frame, k))
        for j, (frame, k) in enumerate(work):
            report("faces", 0.0, j, len(work))
            parts = report.part("filtering", j, len(work)) if req.params.filtering else None
            frame.meshes.append(self._faces(req, frame, k, parts))
            report("faces", 1.0, j, len(work))
        made, errors = [], []
        for frame in frames:
            try:
                made.append(self._choose(req, frame))
            except GenerationError as err:
                errors.append(err)
        return made, errors

    def _frame(self, req: Request, rotation: np.ndarray) -> Frame:
        """The input turned by ``rotation`` (the request's own frame for the identity) with what every stage
        reads of it: the reference the candidates are scored against (None for one candidate), and the cell
        evidence and candidates' encodings (``_encode``), timed as the encode stage."""
        frame = req.frame if np.array_equal(rotation, np.eye(3)) else Frame.of(req.shape, rotation)
        seed, n_cand = req.params.seed, req.candidates
        # Candidate k is exactly what seed + k gives alone; all are scored against one sample of the input.
        frame.reference = frame.surface(self.triangle_config.support_points, seed) if n_cand > 1 else None
        with stage("encode", req.timings):
            frame.logodds = self._logodds(frame)
            frame.encoded = [self._encode(frame, seed + k, req.params, frame.logodds) for k in range(n_cand)]
        return frame

    def _choose(self, req: Request, frame: Frame) -> dict:
        """The frame's candidate nearest its input surface (``support.surface_fit``), turned back to the input's
        frame; raises the first candidate's GenerationError when none made a mesh."""
        n_cand, seed = req.candidates, req.params.seed
        best, fits, errors = None, [], []
        for k, cand in enumerate(frame.meshes):
            if isinstance(cand, GenerationError):
                errors.append(cand)
                fits.append(None)
                continue
            with stage("filtering", req.timings):  # choosing among candidates: a filtering step
                fit = surface_fit(cand["vertices"], cand["faces"], frame.reference, seed) if n_cand > 1 else 0.0
            fits.append(round(float(fit), 6))
            if best is None or fit < best["fit"]:
                best = {**cand, "fit": fit, "seed": seed + k}
        if best is None:
            raise errors[0]
        evidence = best["evidence"].moved(frame.norm.invert(best["evidence"].points) @ frame.rotation)
        info = {"generated_vertices": best["generated_vertices"], "edges": best["edges"], "candidates": n_cand,
                "chosen_seed": best["seed"]}
        if n_cand > 1:
            info["fits"] = fits  # per candidate: its surface_fit in the unit cube, None if it made no mesh
        return {"vertices": frame.norm.invert(best["vertices"]) @ frame.rotation, "faces": best["faces"],
                "tokens": best["tokens"], "info": info, "rotation": frame.rotation, "evidence": evidence}

    def _target(self, params: GenerateParams) -> torch.Tensor | None:
        """(1,) faces asked for, as the decoder's count token reads them (None: the model's choice)."""
        if params.target_faces is None:
            return None
        if not self.vertex.cfg.count_condition:
            raise ValueError("target_faces: this vertex decoder was not trained with a face-count condition")
        return torch.tensor([params.target_faces], device=self.device)

    def _logodds(self, frame: Frame) -> torch.Tensor | None:
        """(1, 128^3) cell log-odds of the input in ``frame`` for a decoder that reads them (``models.cells``),
        else None.

        Evidence about the input, not a random choice: drawn from one sample of fixed seed, so every
        candidate reads the same grid and candidate k stays exactly what seed + k gives alone.
        """
        if not self.vertex.cfg.evidence_cells:
            return None
        pts, nrm = frame.samples(self.cell_net.cfg.n_points, CELL_SEED)
        return self.cell_net.grid(pts, nrm)[None].to(self.device)

    def _encode(self, frame: Frame, seed: int, params: GenerateParams, logodds: torch.Tensor | None = None) -> tuple:
        """The surface sample of ``seed`` in ``frame`` (points, normals: (n, 3) float32 in its unit cube) and the
        vertex decoder's condition on it: (points, normals, prefix (1, M, dim), evidence); ``logodds`` from
        :meth:`_logodds`."""
        pts, nrm = frame.samples(self._n_points(), seed)
        n_vp = self.vertex.cfg.encoder.n_points
        pts_t = torch.from_numpy(pts).to(self.device)[None, :n_vp]
        nrm_t = torch.from_numpy(nrm).to(self.device)[None, :n_vp]
        with torch.inference_mode():
            target = self._target(params)
            prefix = self.vertex.condition(pts_t, nrm_t, target)
            evidence = self.vertex.point_evidence(pts_t, nrm_t, logodds, target)
        return pts, nrm, prefix, evidence

    def _decode(self, req: Request, frames: list[Frame], report: Callable[[float], None]
                ) -> Generator[DecodeRequest, list[torch.Tensor], list[tuple]]:
        """Vertex tokens of every frame's candidates ``params.seed`` ... ``params.seed + n_cand - 1`` (their
        ``encoded`` conditions, from :meth:`_frame`), decoded as one batch: a second frame's rows ride with the
        first's instead of decoding after them.

        Candidate k of a frame reads its own surface sample (seed + k) and samples with seed + k: it is what that
        seed gives alone, in whatever batch (``models.generate``: each row keeps its seed, evidence and grammar
        state).  Yields the :class:`DecodeRequest` of the candidates and is sent their sequences
        (:class:`fastmesh.batch.Batch` decodes it, adds the decoding time to ``req.timings`` and calls the
        request's ``progress``, here ``report(share)`` of the vertices decoded); returns per candidate, frame
        after frame, its (points, normals, tokens).
        """
        req.check()
        encoded = [e for frame in frames for e in frame.encoded]
        seeds = [req.params.seed + k for frame in frames for k in range(len(frame.encoded))]
        evidence = [ev for _, _, _, ev in encoded]
        sampling = req.params.sampling(self.max_vertices)
        max_v = sampling.max_vertices

        def on_step(n_vert: int) -> None:
            report(min(1.0, n_vert / max_v))

        report(0.0)
        seqs = yield DecodeRequest(torch.cat([prefix for _, _, prefix, _ in encoded]),
                                   None if evidence[0] is None else evidence, sampling, seeds, on_step,
                                   req.should_cancel, req.timings)
        return [(pts, nrm, seq.cpu().numpy()) for (pts, nrm, _, _), seq in zip(encoded, seqs, strict=True)]

    def vertex_cells(self, tokens: np.ndarray, logodds: torch.Tensor | None, params: GenerateParams,
                     count: CountRule | None = None) -> np.ndarray:
        """(N, 3) int64 vertex cells of the decoder's ``tokens``, moved by the cell log-odds ``logodds`` (from
        :meth:`_logodds`) where ``SamplingConfig.snap_margin`` says so (``models.cells.snap_to_cells``) and
        the face-count rule allows it (``count``, made from ``params`` when not given: not with a target)."""
        q = vt.decode(tokens, strict=True)
        margin = params.sampling(self.max_vertices).snap_margin
        count = count or count_rule(params.target_faces)
        if logodds is None or margin is None or not count.snap:
            return q
        return snap_to_cells(q, logodds[0].cpu(), margin)

    def _fit(self, frame: Frame, positions: np.ndarray, seed: int) -> np.ndarray:
        """``positions`` (N, 3) moved onto the planes of the input around them (``fitting.fit_to_planes``)."""
        from scipy.spatial import cKDTree

        pts, nrm = fit_samples(frame.shape, frame.unit, self.fit_config, seed, draw=frame.samples)
        tree = cKDTree(pts)
        cfg = self.fit_config
        return fit_to_planes(positions, pts, nrm, fit_radius(cfg, pts, tree), cfg.rel, tree, cfg.reach)

    def _positions(self, req: Request, frame: Frame, k: int) -> tuple | GenerationError:
        """Candidate ``k`` of the frame as vertex cells and positions in its unit cube: ``(cells (N, 3) int64,
        positions (N, 3), vertices decoded)``, or the GenerationError that stops it; timed as the enhancer."""
        pts, nrm, tokens = frame.decoded[k]
        q = self.vertex_cells(tokens, frame.logodds, req.params, req.count)
        if len(q) < 3:
            return GenerationError("no_vertices", f"the vertex decoder produced {len(q)} vertices; try another seed")
        decoded = len(q)
        req.check()
        # Fidelity enhancer: continuous positions inside each cell.
        with stage("enhancer", req.timings):
            if req.params.enhancer:
                n_ep = self.enhancer.cfg.encoder.n_points
                positions = self.enhancer.refine(q, pts[:n_ep], nrm[:n_ep])
            else:
                positions = dequantize(q)
            if self.fit_config.radius is not None:
                positions = self._fit(frame, positions, req.params.seed + k)
                if self.fit_config.merge is not None:  # vertices fitted onto one point become one
                    keep = distinct(positions, self.fit_config.merge * CELL)
                    q, positions = q[keep], positions[keep]
                    if len(q) < 3:
                        return GenerationError("no_vertices", f"the vertex decoder's {decoded} vertices lie on "
                                               f"{len(q)} points of the surface; try another seed")
        return q, positions, decoded

    def _faces(self, req: Request, frame: Frame, k: int, report: Callable[[float], None] | None
               ) -> dict | GenerationError:
        """Candidate ``k``'s mesh in the frame's unit cube from its :meth:`_positions`, its holes closed where
        the request closes (``req.close``), or the GenerationError that stopped it; ``report(share)`` follows the
        filtering passes (None without filtering).  Adds its stage times to ``req.timings``."""
        placed = frame.positions[k]
        if isinstance(placed, GenerationError):
            return placed
        q, positions, decoded = placed
        pts, nrm, tokens = frame.decoded[k]
        timings = req.timings
        req.check()
        # Stage II: edges in one bidirectional pass, then (optionally) filtered re-predictions.
        n_fp = self.face.cfg.encoder.n_points
        with stage("faces", timings):
            predict = self.face.predictor(q, pts[:n_fp], nrm[:n_fp])  # encodes the condition once
        predict = _timed(predict, timings, report or (lambda share: None), req.should_cancel,
                         self.filter_config.n_passes)
        edges, logits = predict_edges(predict, len(q), self.filter_config, req.params.filtering)

        # Triangles on the input surface, scored by the edge logits, kept a surface, holes closed, flat vertices
        # removed (but not below a face-count target: ``req.count.remove_flat``).
        with stage("faces", timings):
            tc = replace(self.triangle_config, close=req.close)
            if not req.count.remove_flat:  # the count asked for: flat regions keep their vertices
                tc = replace(tc, flat_tol=None)
            surface = None
            if tc.support_tol is not None or tc.max_faces_per_edge is not None or tc.selection == "surface":
                surface = frame.surface(tc.support_points, req.params.seed + k)
            verts, faces = mesh_from_adjacency(positions, edges, tc, points=surface, logits=logits)
        if len(faces) == 0:
            return GenerationError("no_faces", f"the face model connected no triangles among {len(q)} vertices")
        return {"vertices": verts, "faces": faces, "tokens": int(len(tokens)), "generated_vertices": decoded,
                "edges": int(len(edges)), "evidence": EdgeEvidence.of_mesh(verts, faces, positions, logits, edges)}
