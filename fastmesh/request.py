"""One generation request as its stages read it, made once by :meth:`fastmesh.pipeline.Pipeline.steps`.

A :class:`Request` holds the input and its parameters, what a face-count target changes
(``facecount.count_rule``), the closedness decision, the progress, cancellation and stage timings, and the
input's own :class:`Frame`.  A :class:`Frame` is the input turned into a frame it is generated in, with its
normalisation and the candidates' work; every stage draws its surface samples there through
:meth:`Frame.samples`, which draws each (count, seed) once and shares it: the plane rebuild, the cell evidence
and the whole step read one draw of ``PLANAR_SAMPLES`` at seed 0, the candidates' scoring and candidate 0's
faces one draw at the request's seed.  Samples of other counts or seeds are other draws (each stage's count
and seed were tuned with it), so results are those of a sample per stage.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np

from .evaluation.quality import input_pieces
from .export.placement import read_up
from .faces.facecount import CountRule, count_rule, input_samples
from .models.generate import Cancelled
from .params import LARGEST_VERTEX_LIMIT, GenerateParams
from .progress import STAGES, Progress
from .shapes.canonical import rotate_shape
from .shapes.io import sample_surface
from .shapes.orientation import oriented
from .shapes.shape import Normalization, Shape

PLANAR_SAMPLES = 8192  # surface samples of a mesh input read by ``planar.polyhedron`` and the whole step


# The stages a request's seconds are counted in: the progress's (``progress.STAGES``), and the weighing of rivals
# (the candidates, the frames, the meshes with missed points or on quadric vertices, the input's decimation, the
# redistributed and edge-turned meshes, the box reached), which the progress shows as part of the face stage.
TIMED_STAGES = (*(name for name, _, _ in STAGES), "weighing")


class StageTimes(dict):
    """Seconds per stage (``TIMED_STAGES``) of one request, counted by a clock that is always in exactly one stage:
    every second from its start to :meth:`stop` lands in one, none twice.  :func:`stage` moves it for a block;
    :meth:`enter` moves it until the next move.  It runs on while the request waits for its batched vertex decoding
    (:mod:`fastmesh.batch`): that wait is the job's ``vertices`` too."""

    def __init__(self, first: str):
        super().__init__({name: 0.0 for name in TIMED_STAGES})
        self.current, self.since, self.running = first, time.perf_counter(), True

    def _lap(self) -> None:
        now = time.perf_counter()
        if self.running:
            self[self.current] += now - self.since
        self.since = now

    def enter(self, name: str) -> str:
        """Count from now in stage ``name``; returns the stage counted until now."""
        if name not in self:
            raise KeyError(f"unknown stage {name!r} (stages: {', '.join(TIMED_STAGES)})")
        self._lap()
        before, self.current = self.current, name
        return before

    def stop(self) -> None:
        """Stop counting (the request is done); idempotent."""
        self._lap()
        self.running = False


@dataclass
class Frame:
    """The input turned by ``rotation`` (the shape as the stages of one frame see it), and their work.

    Attributes
    ----------
    shape : Shape, turned (the input itself for the identity)
    rotation : (3, 3) float64
    norm : Normalization of the turned shape into the unit cube
    unit : (N, 3) float64, the turned shape's vertices in the unit cube
    reference : (M, 3) float32 or None, the input surface the candidates are scored against
    logodds : torch.Tensor or None, (1, 128^3) the cell network's log-odds (``Pipeline._logodds``)
    encoded, decoded, positions, meshes : per candidate, what ``Pipeline`` made of it stage by stage
    """

    shape: Shape
    rotation: np.ndarray
    norm: Normalization
    unit: np.ndarray
    reference: np.ndarray | None = None
    logodds: object = None
    encoded: list = field(default_factory=list)
    decoded: list = field(default_factory=list)
    positions: list = field(default_factory=list)
    meshes: list = field(default_factory=list)
    _drawn: dict = field(default_factory=dict, repr=False)

    @classmethod
    def of(cls, shape: Shape, rotation: np.ndarray | None = None) -> Frame:
        """``shape`` turned by ``rotation`` (3, 3) (default: its own frame) and normalised."""
        rotation = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64)
        if not np.array_equal(rotation, np.eye(3)):
            shape = rotate_shape(shape, rotation)
        norm = Normalization.fit(shape.vertices)
        return cls(shape=shape, rotation=rotation, norm=norm, unit=norm.apply(shape.vertices))

    def samples(self, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """(n, 3) float32 points and unit normals of the surface in the unit cube (``io.sample_surface``),
        drawn once per (n, seed) and shared: callers read them, never write them."""
        key = (int(n), int(seed))
        if key not in self._drawn:
            self._drawn[key] = sample_surface(self.shape, key[0], seed=key[1], vertices=self.unit)
        return self._drawn[key]

    def surface(self, n: int, seed: int) -> np.ndarray:
        """(<= n, 3) points of the surface in the unit cube for the face support check (``io.input_surface``):
        a point cloud of at most ``n`` points gives all of them (resampling would hide their spacing)."""
        if self.shape.faces is None and len(self.unit) <= n:
            return np.asarray(self.unit)
        return self.samples(n, seed)[0]


@dataclass
class Request:
    """One call of ``Pipeline.steps``: what every stage reads, made once.

    Attributes
    ----------
    shape : Shape, the input in its own frame, turned Y-up where ``params.input_up`` is z (a point cloud's normals
        outward: ``Request.start``)
    params : GenerateParams, validated
    count : CountRule, what the face-count target changes (``facecount.count_rule``); told to the decoder once the
        input's cells are read where it lies far under their count (``FrameSteps._frame``)
    report : Progress
    should_cancel : callable or None
    timings : StageTimes, seconds per stage (``TIMED_STAGES``), every second of the request in one
    frame : Frame, the input's own (identity rotation)
    close : bool, whether the result is closed (``closure.decide_closed``); ``reason`` says why: one of
        ``decide_closed``'s, or "open_planes" (an open surface rebuilt from its planes, ``open_planar``)
    sealed : bool, the result is closed and the input is a closed mesh (``closure.without_openings``): it has no
        openings, so the closure closes every loop however far its cap strays (``TriangleConfig.close_everywhere``)
    corners : (K, 3) float64 or None, a mesh input's corners in its own coordinates once found
        (``FrameSteps._corners_in``; every frame reads them turned)
    """

    shape: Shape
    params: GenerateParams
    count: CountRule
    report: Progress
    should_cancel: Callable[[], bool] | None
    timings: StageTimes
    frame: Frame
    close: bool = True
    reason: str = "closed_points"
    sealed: bool = False
    corners: np.ndarray | None = None

    @classmethod
    def start(cls, shape: Shape, params: GenerateParams, progress: Callable[[str, float], None] | None = None,
              should_cancel: Callable[[], bool] | None = None) -> Request:
        """The request of ``shape``: turned Y-up where ``params.input_up`` says it is Z-up
        (``placement.read_up``: every stage, the placement and the quality read it so), a point cloud's normals
        turned outward where they point in (``orientation.oriented``), timed with the encoding."""
        timings = StageTimes("encode")  # reading the input counts with its encoding
        if params.input_up != "y":
            shape = replace(shape, vertices=read_up(shape.vertices, params.input_up),
                            normals=None if shape.normals is None else read_up(shape.normals, params.input_up))
        shape = oriented(shape)
        told = params.sampling(LARGEST_VERTEX_LIMIT).read_count
        return cls(shape=shape, params=params, count=count_rule(params.target_faces, told),
                   report=Progress(progress, params.filtering), should_cancel=should_cancel,
                   timings=timings, frame=Frame.of(shape))

    @property
    def decision(self) -> dict:
        return {"close": self.close, "reason": self.reason}

    @property
    def candidates(self) -> int:
        """Candidates made per frame: ``params.candidates``, one with greedy decoding (one answer)."""
        return self.params.candidates if self.params.temperature > 0 else 1

    def check(self) -> None:
        """Raise :class:`Cancelled` where the caller asks to stop."""
        if self.should_cancel is not None and self.should_cancel():
            raise Cancelled("generation cancelled")

    @cached_property
    def surface_points(self) -> np.ndarray:
        """(M, 3) float64 points of the input surface in its own frame: a point cloud's own, a mesh's
        ``PLANAR_SAMPLES`` samples at seed 0 (the draw the plane rebuild and the cell evidence read)."""
        if self.shape.faces is None:
            return np.asarray(self.shape.vertices, dtype=np.float64)
        return self.frame.norm.invert(self.frame.samples(PLANAR_SAMPLES, 0)[0])

    @cached_property
    def count_samples(self) -> tuple[np.ndarray, np.ndarray]:
        """(M, 3) points and normals of the input surface in its own frame for ``facecount.hold_count``."""
        return input_samples(self.shape)

    @cached_property
    def pieces_in(self) -> int:
        """The input's pieces (``quality.input_pieces``), read by the whole step and the report."""
        return input_pieces(self.shape)
