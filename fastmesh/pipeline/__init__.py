"""The two-stage FastMesh pipeline: load the networks once, then ``generate`` many times.

The stages as :meth:`Pipeline.generate` runs them (``STAGES`` names their progress; ``request.TIMED_STAGES`` their
timings, in which every second of a call is counted once: reading the input with the encoding, and the weighing of
rivals in ``weighing``):

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
          ──► the candidate nearest the input surface (``support.weighed_fit``), weighing
              and the rivals of the chosen one
          ──► back to the input's frame, made whole, closed where it must be   faces
              (``closing``), then the vertices that stand for no turn of   weighing
              its shape collapsed (``finish.coarsened_closed``)
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

import os
from collections.abc import Callable, Generator, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch

from ..batch import DecodeRequest
from ..faces.closure import decide_closed, without_openings
from ..faces.filtering import FilterConfig
from ..faces.triangles import TriangleConfig
from ..fitting import FitConfig
from ..models.checkpoint import load_model, save_model
from ..models.encoder import EncoderConfig
from ..models.generate import Cancelled, GenerationError
from ..models.onnx_decode import choose_decoder
from ..params import GenerateParams
from ..progress import STAGES
from ..request import Request
from ..shapes.canonical import canonical_rotation, frame_normals, turned_degrees
from ..shapes.shape import Shape
from . import result as step8
from .candidate import CELL_SEED
from .closing import closed_result
from .finish import coarsened_closed, last_steps
from .frames import FrameSteps
from .result import GenerateResult
from .runtime import CPU_THREADS, STAGE_THREADS, auto_device, choose_threads, stage
from .settings import CELL_NET_DIR, NETWORKS, default_weights_dir, read_settings, write_settings

# ``Pipeline.random``'s support limit, relative to the input's size: its decoder's vertices lie anywhere.
RANDOM_SURFACE_TOL = 1.0

__all__ = ["CELL_SEED", "CPU_THREADS", "STAGES", "STAGE_THREADS", "Cancelled", "GenerateParams", "GenerateResult",
           "GenerationError", "Pipeline", "auto_device", "choose_threads", "default_weights_dir"]


class Pipeline(FrameSteps):
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
        self.triangle_config = triangle_config or TriangleConfig()
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
        configs = read_settings(root / "pipeline.json")
        return cls(nets["vertex"], nets["enhancer"], nets["face"], device=dev, source=str(root), threads=threads,
                   cell_net=cell_net, **configs)

    @classmethod
    def random(cls, size: str = "tiny", seed: int = 0, device: str | None = None,
               threads: int | None = None) -> Pipeline:
        """Randomly initialised networks, for tests and benchmarks of the machinery.

        ``tiny`` networks are a few thousand parameters.  A random face model would
        predict no edges; its output bias is set so every pair connects, which gives a
        (meaningless) mesh on every input, so the service can be tested end to end.
        The face stage is the shipped one (:class:`TriangleConfig`'s defaults) but for its support limit:
        a random decoder's vertices lie anywhere in the unit cube, so a candidate triangle may stray from
        the input by the input's size (``surface_tol`` 1.0); and a mesh input's decimation and the vertices of its
        quadrics are not weighed (``weigh_decimation``, ``quadric_vertices``: they would replace every such mesh),
        nor a point cloud's result redistributed or its edges split, nor edges turned, nor input points added to its
        vertices, nor its box brought to the input's, nor its flat regions outlined or its vertices collapsed
        (``redistribute``, ``refine``, ``swap_edges``, ``add_missed``, ``reach_extent``, ``outline``, ``coarsen``: its
        meshes mean nothing, tests would pay for it, and a result stays its chosen candidate's mesh).
        Keep ``max_vertices`` small with it.
        """
        from ..models.enhancer import Enhancer, EnhancerConfig
        from ..models.face import FaceModel, FaceModelConfig
        from ..models.vertex import VertexConfig, VertexDecoder

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
                   threads=threads, triangle_config=TriangleConfig(surface_tol=RANDOM_SURFACE_TOL,
                                                                 weigh_decimation=False, redistribute=None,
                                                                 refine=None, swap_edges=False, add_missed=None,
                                                                 quadric_vertices=False, reach_extent=False,
                                                                 outline=False, coarsen=None))

    def save(self, directory: str | os.PathLike) -> None:
        """Write the networks and ``pipeline.json`` (every setting of the face stage and the fit, whole) so
        ``from_pretrained`` loads this pipeline as it is."""
        root = Path(directory)
        for name, net in zip(NETWORKS, (self.vertex, self.enhancer, self.face), strict=True):
            save_model(net, name, root / name)
        if self.cell_net is not None:
            save_model(self.cell_net, CELL_NET_DIR, root / CELL_NET_DIR)
        write_settings(root / "pipeline.json", self.filter_config, self.triangle_config, self.fit_config)

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
        (:func:`fastmesh.faces.support.weighed_fit`): a sampled mesh sometimes leaves out a part or fills
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
        from ..batch import Batch

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

    def _unrun(self, req: Request, vertices: np.ndarray, faces: np.ndarray, source: str) -> GenerateResult:
        """The result of a request the networks did not run for: rebuilt from planes, simplified within a flat-faced
        input's surface, or the input itself; closed where the request closes it (``closing.closed_result``);
        brought to a ``target_faces`` (``step8.held``): the input's own surface split or simplified is nearer it
        than anything generated.  A cancel asked while it was made stops it here (the flat simplification can take
        seconds)."""
        req.check()
        req.timings.enter("faces")
        info, step = {"turned_degrees": 0.0, "result_from": source, "vertices_from": source}, None
        vertices, faces, note = closed_result(req, vertices, faces, self.triangle_config)
        if req.count.hold:
            info["faces_before_count"] = int(len(faces))
            vertices, faces, step = step8.held(req, vertices, faces)
        result = step8.finished(req, vertices, faces, tokens=0, info=info, count_step=step, note=note)
        return self._done(req, result, "faces")

    @staticmethod
    def _done(req: Request, result: GenerateResult, stage: str | None = None) -> GenerateResult:
        """``result`` with the request's stage timings, its clock stopped once the progress says done."""
        if stage is None:
            req.report.done()
        else:
            req.report.done(stage)
        req.timings.stop()
        result.timings = dict(req.timings)
        return result

    def steps(self, shape: Shape, params: GenerateParams | None = None,
              progress: Callable[[str, float], None] | None = None, should_cancel: Callable[[], bool] | None = None
              ) -> Generator[DecodeRequest, list[torch.Tensor], GenerateResult]:
        """:meth:`generate` as a generator that stops where it needs the vertex decoder: it yields a
        :class:`fastmesh.batch.DecodeRequest` (one per frame) and is sent that request's token sequences (one
        per candidate); it returns the result.  :class:`fastmesh.batch.Batch` runs several at once."""
        params = params or GenerateParams()
        params.validate(limit=self.max_vertices)
        self._target(params, params.sampling(self.max_vertices).read_count)  # refused before any work: no token
        req = Request.start(shape, params, progress, should_cancel)
        unrun = self._unrun_closed(req, params)
        if unrun is not None:
            return unrun
        turn = canonical_rotation(req.shape.vertices, frame_normals(req.shape))
        unrun = self._unrun_open(req, params, turn)
        if unrun is not None:
            return unrun
        # The input's own frame, and its canonical one where that lays more of its walls along the axes
        # (``canonical``): each is generated, and the mesh nearer the input kept.
        frames = [np.eye(3)]
        if not np.array_equal(turn, frames[0]):
            frames.append(turn)
        made, errors = yield from self._in_frames(req, frames)
        if not made:
            raise errors[0]
        return self._finished(req, self._nearest_frame(req, made))

    def _unrun_closed(self, req: Request, params: GenerateParams) -> GenerateResult | None:
        """The result, where the networks need not run, of a closed input's planes, a low-poly input given back or a
        flat-faced input simplified (see :meth:`_unrun`); None where they must run.  Decides whether the result is
        closed (``req.close``, ``req.reason``, ``req.sealed``) on the way."""
        shape = req.shape  # a point cloud's normals turned outward
        # A point cloud that bounds a polyhedron is closed: the winding numbers are read only where it does not.
        cheap = shape.faces is not None or params.closed != "auto"
        if cheap:
            req.close, req.reason = decide_closed(shape, params.closed)
            req.sealed = req.close and (req.reason == "closed_mesh" or without_openings(shape))
        flat = step8.planar(req) if req.close else None
        if flat is not None:
            return self._unrun(req, *flat)
        if not cheap:
            req.close, req.reason = decide_closed(shape, params.closed)
        few = step8.low_poly(shape, step8.FEW_FACES) if req.count.low_poly_input else None
        if few is not None and params.closed == "true":  # given back only where it closes without the networks
            few = closed_result(req, *few, self.triangle_config)
            few = few[:2] if few[2] is None else None
        if few is not None:
            return self._unrun(req, *few, "input")
        simple = step8.flat_faced(req)
        return None if simple is None else self._unrun(req, *simple)

    def _unrun_open(self, req: Request, params: GenerateParams, turn: np.ndarray) -> GenerateResult | None:
        """An open piecewise-planar surface (a ramp, a roof without its floor) from its planes, seen in the
        canonical frame ``turn``, unless the request asks for a closed result; None where there is none.  Where
        the points stop on the sides of its box, there is no surface, whatever the winding numbers decided."""
        flat = step8.planar(req, open_=True, turn=turn) if params.closed != "true" else None
        if flat is None:
            return None
        req.close, req.reason = False, "asked" if params.closed == "false" else "open_planes"
        return self._unrun(req, *flat)

    def _finished(self, req: Request, best: dict) -> GenerateResult:
        """The result of the frame ``best`` (:meth:`_nearest_frame`): made whole, weighed against its rivals and
        brought to a count (``finish.last_steps``), closed, coarsened where it has more faces than its shape needs
        (``finish.coarsened_closed``) and finished."""
        req.timings.enter("faces")
        # The boundary of a solid is free of folds: the steps after it keep it so (``crossings``).
        solid = best["info"].get("solid_fits", {}).get("faces_from") == "solid"
        vertices, faces, result_from, pulled = step8.whole(req, best["vertices"], best["faces"], uncrossed=solid)
        info = {**best["info"], "turned_degrees": round(turned_degrees(best["rotation"]), 3), "pulled_in": pulled}
        vertices, faces, result_from, step = last_steps(req, vertices, faces, info, result_from, self.triangle_config)
        if result_from != "model":  # the decimation's, or a low-poly input's own
            info["vertices_from"] = result_from
        with stage("faces", req.timings):
            vertices, faces, note = closed_result(req, vertices, faces, self.triangle_config,
                                                  uncrossed=solid and result_from == "model")
        if result_from == "model" and not req.count.hold:
            vertices, faces = coarsened_closed(req, vertices, faces, info, self.triangle_config)
        faces = step8.facing(req, vertices, faces)
        result = step8.finished(req, vertices, faces, tokens=best["tokens"], info={**info, "result_from": result_from},
                                evidence=best["evidence"] if result_from == "model" else None, count_step=step,
                                note=note)
        return self._done(req, result)
