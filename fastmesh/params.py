"""User-facing generation parameters and the values each accepts (no torch import: the CLI and service read
them cheaply).

Each parameter is declared once, as a field of :class:`GenerateParams` (its type, default and help), with its
values in ``BOUNDS`` (numbers) or ``CHOICES`` (strings).  :data:`PARAMETERS` presents them to the interfaces,
which make their own from it: the service's form fields (``service.routes.form``, whose OpenAPI schema states
the same ranges), the command-line flags (``fastmesh.cli.flags``), the web page's inputs
(``service.web.routes.page_config``).  ``GenerateParams.validate`` (library, CLI, worker) and
``SamplingConfig.validate`` (the decoder's loop) check ``BOUNDS``.
"""

from __future__ import annotations

import typing
from dataclasses import asdict, dataclass, field, fields, replace

MAX_CANDIDATES = 16  # each candidate costs a full generation
TARGET_FACES = (4, 8000)  # faces a user may ask for; the decoder's vertex limit still caps the result
# Smallest non-zero temperature: logits / temperature must stay finite in float32 (0 means greedy decoding).
MIN_TEMPERATURE = 1e-3
MAX_TEMPERATURE = 5.0
DEFAULT_VERTEX_LIMIT = 1000  # a vertex decoder's max_vertices unless its config says otherwise
LARGEST_VERTEX_LIMIT = 4000  # the largest max_vertices of a trained decoder: the limit while the model is unknown
# ``closed``: close the result's holes when the input is closed (auto), always (true) or never (false).
CLOSED_CHOICES = ("auto", "true", "false")
# ``topology``: triangles, or quads where two triangles make a near-planar, well-shaped one (fastmesh.export.quads).
TOPOLOGY_CHOICES = ("triangle", "quad")
# ``origin``: the input's own frame, or the pivot at the result's bounding-box centre or bottom centre.
ORIGIN_CHOICES = ("input", "center", "bottom")
# ``up``: the up axis of the OBJ and PLY files (the result is Y-up, glTF's convention; a GLB is Y-up);
# ``input_up``: the input's up axis (Y, as glTF and most exporters write it, or Z, as CAD and some engines do).
UP_CHOICES = ("y", "z")


@dataclass(frozen=True)
class Bound:
    """The values of one numeric parameter: ``lo`` to ``hi``, both included unless ``lo_open``.

    ``integer`` parameters must be Python ints; the others anything ``float`` reads.  With ``zero``, 0 is
    accepted too (below ``lo``: a value that switches a feature off).
    """

    lo: float
    hi: float
    integer: bool = True
    lo_open: bool = False
    zero: bool = False
    zero_means: str = ""  # what 0 does, named in the error message
    none: bool = False  # None is accepted too (a setting switched off)

    def check(self, name: str, value, hi: float | None = None) -> None:
        """Raise ValueError naming ``name`` unless ``value`` lies in the bound (``hi`` lowers its top)."""
        hi = self.hi if hi is None else hi
        if value is None and self.none:
            return
        if self.integer:
            if not (isinstance(value, int) and self.lo <= value <= hi):
                raise ValueError(f"{name} must be an integer in [{self.lo}, {hi}]")
            return
        try:
            x = float(value)
        except (TypeError, ValueError):
            x = float("nan")  # fails every comparison below
        above_lo = x > self.lo if self.lo_open else x >= self.lo
        if not ((self.zero and x == 0) or (above_lo and x <= hi)):
            zero = f"0 ({self.zero_means}) or " if self.zero and self.zero_means else "0 or " if self.zero else ""
            raise ValueError(f"{name} must be {zero}in "
                             f"{'(' if self.lo_open else '['}{self.lo:g}, {hi:g}]")

    def form_range(self) -> dict:
        """``ge``/``le`` of a form field or schema holding this bound (with ``zero``, from 0: the values between
        0 and ``lo`` are refused by :meth:`check` alone)."""
        if self.zero:
            return {"ge": 0, "le": self.hi}
        return {"gt" if self.lo_open else "ge": self.lo, "le": self.hi}


BOUNDS = {
    # Candidate k samples with seed + k: every such seed must stay a valid int64 generator seed.
    "seed": Bound(0, 2**63 - 1 - MAX_CANDIDATES),
    "temperature": Bound(MIN_TEMPERATURE, MAX_TEMPERATURE, integer=False, zero=True, zero_means="greedy"),
    "top_k": Bound(0, 1_000_000),  # 0 disables it; the cap keeps the number a sane size
    "top_p": Bound(0.0, 1.0, integer=False, lo_open=True),
    "max_vertices": Bound(3, 1_000_000),  # the decoder's own limit lowers the top (``validate``)
    "candidates": Bound(1, MAX_CANDIDATES),
    "target_faces": Bound(*TARGET_FACES),
    # The decoder's sampling loop only (SamplingConfig): see models.generate.choose_next and pace_mask.
    "structure_temperature": Bound(MIN_TEMPERATURE, MAX_TEMPERATURE, integer=False, zero=True, zero_means="greedy"),
    "cell_weight": Bound(0.0, 20.0, integer=False),
    "pace": Bound(0.1, 100.0, integer=False, zero=True, zero_means="off"),
    "snap_margin": Bound(0.0, 24.0, integer=False, none=True),  # log-odds (None: off)
    "corner_logodds": Bound(-24.0, 24.0, integer=False, none=True),  # log-odds (None: off)
    "read_count": Bound(0, 1),  # a bool
    "tell_below": Bound(0.0, 100.0, integer=False),  # faces per expected vertex (0: never)
    # Metres the result is scaled to stand (0.1 mm to 100 km): a scale that stays a sane size.
    "height": Bound(1e-4, 1e5, integer=False),
}
# The string parameters and the values each takes.
CHOICES = {"closed": CLOSED_CHOICES, "topology": TOPOLOGY_CHOICES, "origin": ORIGIN_CHOICES, "up": UP_CHOICES,
           "input_up": UP_CHOICES}


def _param(default, help: str, **presented):
    """A ``GenerateParams`` field: its default, and how the interfaces present it (:class:`Parameter`).

    ``help`` says what the parameter does (lower case, no final stop); ``presented`` may hold ``unset`` (what
    None does, for a field whose default is None), ``output`` (True: a setting of the written result,
    ``fastmesh.export.output``), ``metavar`` (the CLI's name of its value) and ``example`` (the schema's).
    """
    return field(default=default, metadata={"help": help, **presented})


@dataclass
class GenerateParams:
    """User-facing generation settings: the one declaration of each parameter.

    The service's form fields, the ``generate`` / ``submit`` / ``loadtest`` flags, the web page's inputs and
    the HTTP client's fields are made from these fields (:data:`PARAMETERS`), with the values ``BOUNDS`` and
    ``CHOICES`` state.  Where a default is None the pipeline decides: ``max_vertices`` the vertex model's
    limit, ``target_faces`` the face count (the model chooses it itself).
    """

    seed: int = _param(0, "sampling seed", example=0)
    temperature: float = _param(0.3, "sampling temperature, 0 = greedy")
    top_k: int = _param(50, "top-k sampling, 0 = off")
    top_p: float = _param(0.95, "nucleus sampling")
    max_vertices: int | None = _param(None, "vertex budget", unset="the model's limit", metavar="N")
    enhancer: bool = _param(True, "run the fidelity enhancer (7-bit cell centres)")
    # Prediction filtering (masked re-predictions of the edges) changes none of the faces the surface
    # selection keeps, on the out-of-package eval set (docs/results.md), and costs four more network
    # passes: available, off by default.
    filtering: bool = _param(False, "prediction filtering: masked re-predictions of the edges")
    candidates: int = _param(2, "meshes sampled (seeds seed, seed+1, ...); the one nearest the input is returned; "
                                "1 is fastest")
    target_faces: int | None = _param(
        None, "faces to aim for, held within 20 % (the result's quality gives target_faces, faces and target_met)",
        unset="the model chooses the count from the shape", metavar="N", example=300)
    # "auto" closes the result when the input is closed (``fastmesh.faces.closure.decide_closed``).
    closed: str = _param("auto", "close the result's holes: auto = when the input is closed (a closed mesh, or "
                                 "oriented points that enclose a volume); the decision is in the result's quality",
                         example="auto")
    # The written result (fastmesh.export.output): quads, a UV layout, the input's texture baked onto it, placement.
    topology: str = _param("triangle", "triangles, or quad: pairs of triangles that make a near-planar, "
                                       "well-shaped quad become one, in the OBJ and PLY files (GLB holds triangles); "
                                       "the result's quality.quad_share says how many", output=True, example="quad")
    uv: bool = _param(False, "give the result a UV layout (xatlas), in the GLB (TEXCOORD_0) and OBJ (vt) files",
                      output=True)
    bake: bool = _param(False, "with uv: bake a textured glTF input's base colour onto the layout, into the GLB's "
                               "texture", output=True)
    origin: str = _param("input", "where the result's origin lies: the input's own frame, its bounding box's centre "
                                  "or its bottom centre (Y up)", output=True, example="bottom")
    height: float | None = _param(None, "scale the result to stand this many metres tall along Y",
                                  unset="the input's size", output=True, metavar="METRES", example=1.8)
    up: str = _param("y", "up axis of the OBJ and PLY files; GLB is always Y-up, as glTF requires", output=True,
                     example="z")
    # Read before anything else (``request.Request.start``): the result, its origin and height are Y-up.
    input_up: str = _param("y", "up axis of the input: z turns a Z-up input Y-up ((x, y, z) -> (x, z, -y)) before "
                                "it is generated, placed and measured", example="z")

    def validate(self, limit: int = LARGEST_VERTEX_LIMIT) -> None:
        """Raise ValueError naming the first bad field; ``limit`` is the vertex decoder's ``max_vertices``."""
        for name in (f.name for f in fields(self) if f.name in BOUNDS):
            bound, value = BOUNDS[name], getattr(self, name)
            if value is None and getattr(GenerateParams, name) is None:  # unset: the pipeline decides
                continue
            bound.check(name, value, hi=min(bound.hi, limit) if name == "max_vertices" else None)
        for name, choices in CHOICES.items():
            if getattr(self, name) not in choices:
                raise ValueError(f"{name} must be one of {', '.join(choices)}, got {getattr(self, name)!r}")
        if self.bake and not self.uv:
            raise ValueError("bake needs uv=true: the texture is baked onto the result's UV layout")

    def sampling(self, limit: int) -> SamplingConfig:
        """The decoder's ``SamplingConfig`` with ``max_vertices`` resolved against ``limit``."""
        max_v = limit if self.max_vertices is None else min(int(self.max_vertices), limit)
        return SamplingConfig(temperature=float(self.temperature), top_k=int(self.top_k), top_p=float(self.top_p),
                              max_vertices=max_v, seed=int(self.seed))


@dataclass(frozen=True)
class SamplingConfig:
    """What the vertex decoder's sampling loop reads: ``GenerateParams``' sampling fields, with their defaults,
    and a resolved vertex budget.  ``GenerateParams.sampling`` builds one from a request."""

    temperature: float = GenerateParams.temperature
    top_k: int = GenerateParams.top_k
    top_p: float = GenerateParams.top_p
    max_vertices: int = DEFAULT_VERTEX_LIMIT
    seed: int = GenerateParams.seed
    # Each token is chosen in two steps (models.generate.choose_next): its kind (the end, a new block, another
    # vertex in this block) from the decoder's probabilities at structure_temperature, then which token of that
    # kind at ``temperature``.  One temperature for both sharpened the decoder's many stay-or-go decisions: at 0.3
    # it ended big shapes after one vertex per block (an airliner: 38 vertices for 1,685) and ran away on small
    # ones (docs/results.md).
    structure_temperature: float = 1.0
    # Weight of the cell evidence's log-odds in the choice among a block's offsets (1: as trained); the share
    # of the offsets as a kind is the decoder's own, so the count does not move with it.  On the held-out
    # packages (the previous cell network) 6 and 10 did alike, 3 worse in both precision and recall.  Not with a
    # face-count target: it ends blocks early (``Evidence.weighted_cells``).
    cell_weight: float = 6.0
    # Another vertex in the current block only while the vertices emitted stay under pace x the cells' expected
    # vertices up to this block + models.generate.PACE_SLACK (0: off; decoders that read the cells).  The cells'
    # expected count runs above the artist's (decoded, the held-out packages' median count is 1.36x the
    # reference's at pace 1, 1.11x at 0.8), but the face stage removes the vertices of flat regions
    # (``TriangleConfig.flat_tol``): end to end on the held-out packages, pace 0.8 gave P@1 0.462 / R@1 0.348
    # (seed 0); means of seeds 0 and 7: 1.0 0.427 / 0.358, 1.1 0.424 / 0.368, 1.2 0.414 / 0.367
    # (docs/results.md).  Scaled to a face-count target they are paced at 1: the target is the count asked for.
    pace: float = 1.1
    # After decoding, each vertex moves to the best cell among its own and the 26 around it where that cell's
    # log-odds exceed its own by more than this, and vertices that meet become one (None: off; decoders that
    # read the cells; not with a face-count target: the merges lower the count; models.cells.snap_to_cells).
    # On the held-out packages, end to end: off CD 1.33 / HD 8.40, P@1 0.347 / R@1 0.348, count median 1.11;
    # 0: 1.37 / 8.73, 0.354 / 0.335, 0.78; 1: 1.27 / 8.51, 0.356 / 0.345, 0.96; 2: 1.29 / 8.55, 0.353 / 0.348
    # (docs/results.md).
    snap_margin: float | None = 1.0
    # A mesh input's corners (``shapes.corners``: where three of its planes meet at creases) raise their cells'
    # log-odds to at least this, so the decoder emits a vertex there (None: off).  On the 60 held-out mesh
    # inputs, off: P@1 0.499 / R@1 0.392, CD 1.45; 8: 0.560 / 0.472, 1.42 (docs/results.md); 3 did a little
    # worse than 8 in a first measure.
    corner_logodds: float | None = 8.0
    # A ``target_faces`` told to a decoder trained to read it (its count token, and the cells' expected vertices
    # scaled to it), which then keeps the vertices it made for that count; off, the decoder makes its own count
    # and the result is brought to the target (``facecount.hold_count``).  Told, it follows the count loosely and
    # breaks above its own: on held-out point clouds at 2-4x their reference's faces, CD 2.03-2.55 against 1.02-1.54
    # split from its own result (slivers, open, in pieces; curved shapes up to 13), in three times as long
    # (benchmarks/count_told.py, docs/results.md).
    read_count: bool = False
    # ... but told where the target lies under ``tell_below`` x the vertices the cells expect (before decoding):
    # there the model's own result has far more faces than asked (0.49-1.44 faces per expected vertex on the
    # held-out point clouds, 10th to 90th percentile), and collapses that many stop short or lose thin parts (a
    # grenade's 122 faces to 16: 74 left, CD 3.64) where the decoder told the count places fewer vertices itself
    # (16 faces, 2.31).  0: never told.
    tell_below: float = 0.5

    def validate(self) -> None:
        """Raise ValueError naming the first field outside ``BOUNDS``."""
        for f in fields(self):
            BOUNDS[f.name].check(f.name, getattr(self, f.name))


class TunedParams(GenerateParams):
    """A request whose decoder settings carry ``overrides`` (``SamplingConfig`` fields a user does not set):
    how the benchmarks and ``fastmesh eval --sampling`` measure a setting before it becomes a default."""

    def __init__(self, overrides: dict, params: GenerateParams | None = None):
        super().__init__(**asdict(params or GenerateParams()))
        known = {f.name for f in fields(SamplingConfig)} - {f.name for f in fields(GenerateParams)}
        if not isinstance(overrides, dict) or set(overrides) - known:
            raise ValueError(f"sampling overrides are an object of SamplingConfig fields ({', '.join(sorted(known))}),"
                             f" got {overrides!r}")
        for name, value in overrides.items():
            BOUNDS[name].check(name, value)
        self.overrides = dict(overrides)

    def sampling(self, limit: int) -> SamplingConfig:
        return replace(super().sampling(limit), **self.overrides)



@dataclass(frozen=True)
class Parameter:
    """One ``GenerateParams`` field as the interfaces present it: form field, CLI flag, page input.

    ``type`` is int, float, bool or str (a choice among ``choices``); ``bound`` its ``BOUNDS`` entry, if any.
    """

    name: str
    type: type
    default: object
    help: str
    unset: str = ""
    bound: Bound | None = None
    choices: tuple[str, ...] = ()
    output: bool = False
    metavar: str | None = None
    example: object = None

    @property
    def flag(self) -> str:
        """The command-line flag: ``--target-faces`` for ``target_faces`` (a bool adds ``--no-...``)."""
        return "--" + self.name.replace("_", "-")

    def described(self, default: str) -> str:
        """``help`` with what an unset value does: ``default`` words the default (``"default 0.3"``)."""
        return f"{self.help}; unset = {self.unset}" if self.default is None and self.unset else \
            f"{self.help} ({default})"


def _parameters() -> tuple[Parameter, ...]:
    hints = typing.get_type_hints(GenerateParams)
    out = []
    for f in fields(GenerateParams):
        kind = next(t for t in typing.get_args(hints[f.name]) or (hints[f.name],) if t is not type(None))
        out.append(Parameter(f.name, kind, f.default, bound=BOUNDS.get(f.name), choices=CHOICES.get(f.name, ()),
                             **f.metadata))
    return tuple(out)


PARAMETERS = _parameters()  # in the order of GenerateParams' fields
