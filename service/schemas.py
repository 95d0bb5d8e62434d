"""Response models: they document the API (OpenAPI with examples); the handlers return plain dicts."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

Status = Literal["queued", "running", "succeeded", "failed", "cancelled"]

JOB_EXAMPLE = {
    "id": "3f2b9c1d4e5f40718293a4b5c6d7e8f9",
    "status": "succeeded",
    "progress": {"stage": "done", "fraction": 1.0},
    "created_at": "2025-05-01T12:00:00.000000Z",
    "started_at": "2025-05-01T12:00:00.210000Z",
    "finished_at": "2025-05-01T12:00:04.870000Z",
    "params": {"seed": 0, "temperature": 0.3, "top_k": 10, "top_p": 0.95, "max_vertices": 1000,
               "enhancer": True, "filtering": False, "candidates": 2, "target_faces": None, "closed": "auto",
               "topology": "triangle", "uv": False, "bake": False, "origin": "input", "height": None, "up": "y",
               "input_up": "y", "formats": ["glb"]},
    "input": {"filename": "chair.ply", "kind": "points", "points": 20000, "vertices": None, "faces": None},
    "result": {"vertices": 412, "faces": 806, "tokens": 412, "formats": ["glb"], "seed": 1, "result_from": "model",
               "vertices_from": "decoder",
               "quality": {"cd": 2.61, "hd": 11.4, "boundary_edges": 0, "non_manifold_edges": 0,
                           "non_manifold_vertices": 0, "components": 1, "pieces": 1, "input_pieces": 1,
                           "watertight": True, "box_gap": 0.0, "closed_decision": "closed", "faces": 806,
                           "target_faces": None, "target_met": None, "count_step": None, "quads": 0,
                           "quad_share": 0.0, "back_face_share": 0.0, "misoriented_edges": 0,
                           "misoriented_area": 0.0, "self_intersections": 0, "unwelded_vertices": 0},
               "placement": {"scale": 1.0, "offset": [0.0, 0.0, 0.0], "up": "y"}, "notes": []},
    "timings": {"queue": 0.21, "load": 0.05, "encode": 0.12, "vertices": 3.1, "enhancer": 0.2, "faces": 0.9,
                "filtering": 0.0, "weighing": 0.25, "export": 0.02, "total": 4.64},
    "error": None,
    "expires_at": "2025-05-02T12:00:04.870000Z",
    "webhook": {"url": "https://example.com/fastmesh-hook", "state": "delivered", "attempts": 1, "last_status": 200,
                "last_error": None, "last_attempt_at": "2025-05-01T12:00:05.010000Z", "next_attempt_at": None},
}


class ErrorDetail(BaseModel):
    code: str = Field(description="Stable machine-readable reason, e.g. 'unreadable', 'queue_full'.")
    message: str = Field(description="What went wrong, for people.")


class ErrorBody(BaseModel):
    error: ErrorDetail
    model_config = ConfigDict(json_schema_extra={
        "examples": [{"error": {"code": "unreadable", "message": "cannot parse .ply file: ..."}}]})


class Progress(BaseModel):
    stage: str | None = Field(description="queued, starting, encode, vertices, enhancer, faces, filtering, export, "
                                          "done, failed or cancelled.")
    fraction: float = Field(description="Overall fraction of the job done, 0..1 (non-decreasing while it runs).")


class InputInfo(BaseModel):
    filename: str
    kind: Literal["mesh", "points"]
    points: int | None = Field(description="Number of points of a point cloud (null for a mesh).")
    vertices: int | None = Field(description="Vertices of a mesh input (null for a point cloud).")
    faces: int | None = Field(description="Faces of a mesh input (null for a point cloud).")


class Quality(BaseModel):
    """How far the result lies from the input and what its topology is (fastmesh.evaluation.quality)."""

    cd: float = Field(description="Chamfer distance between result and input, % of the input's longest side, "
                                  "from samples of each to the other's surface (an exact result reads about 0).")
    hd: float = Field(description="Hausdorff distance between result and input, % of the input's longest side, "
                                  "measured as cd is.")
    boundary_edges: int = Field(description="Edges with one face: the rims of holes and open borders.")
    non_manifold_edges: int = Field(description="Edges with three or more faces.")
    non_manifold_vertices: int | None = Field(None, description="Vertices whose faces form more than one fan "
                                                                "(pieces touching at a point).")
    components: int = Field(description="Pieces of the mesh (faces connected through shared vertices).")
    pieces: int | None = Field(None, description="Pieces of the mesh (faces connected through shared edges).")
    input_pieces: int | None = Field(None, description="The input's pieces: a mesh's (vertices welded), or a point "
                                                       "cloud's groups of nearby points.")
    watertight: bool = Field(description="Every edge in exactly two faces.")
    box_gap: float | None = Field(None, description="The largest distance between a side of the result's "
                                                    "axis-aligned box and the same side of the input's, % of the "
                                                    "input's longest side.")
    closed_decision: str | None = Field(None, description="closed or open (closed=auto, decided from the input: a "
                                                          "closed mesh, or oriented points enclosing a volume), or "
                                                          "asked (closed=true/false); not_closed where the result "
                                                          "was to be closed and keeps open edges or edges of three "
                                                          "or more faces (notes say which).")
    faces: int | None = Field(None, description="Faces of the result.")
    target_faces: int | None = Field(None, description="Faces asked for (null: the model chose).")
    target_met: bool | None = Field(None, description="faces within 20 % of target_faces (null without a target).")
    count_step: Literal["kept", "simplified", "split", "decimated"] | None = Field(
        None, description="How the count was held: kept (the mesh was within 10 % already), simplified (edges "
                          "collapsed), split (edges split, the new vertices on the input surface) or decimated (the "
                          "input mesh's own decimation to the count came back); null without a target.")
    back_face_share: float | None = Field(None, description="Of what 14 views around the result show, the share "
                                                            "that is the back of a face, 0..1.")
    misoriented_edges: int | None = Field(None, description="Interior edges whose two faces run them the same way "
                                                            "(faces wound against their neighbours).")
    misoriented_area: float | None = Field(None, description="The area wound against the rest of its piece, share "
                                                             "of the result's area, 0..0.5.")
    self_intersections: int | None = Field(None, description="Pairs of faces sharing no vertex that cross each "
                                                             "other.")
    unwelded_vertices: int | None = Field(None, description="Vertices coinciding with another vertex of a "
                                                            "different index.")
    quads: int | None = Field(None, description="Quads in the OBJ and PLY files (topology=quad).")
    quad_share: float | None = Field(None, description="The quads' share of the polygons of the OBJ and PLY files, "
                                                       "0..1 (0 with topology=triangle).")


class Placement(BaseModel):
    """How the result was placed (origin, height, up): a point ``v`` of the input's frame (turned (x, y, z) ->
    (x, z, -y) first for input_up=z) is written at ``v * scale + offset`` (Y-up), then turned (x, y, z) ->
    (x, -z, y) in the OBJ and PLY files for up=z."""

    scale: float
    offset: list[float]
    up: Literal["y", "z"]


class ResultInfo(BaseModel):
    vertices: int
    faces: int
    tokens: int = Field(description="Vertex tokens generated.")
    formats: list[str] = Field(description="Formats exported with the job; the others are converted on request.")
    seed: int | None = Field(None, description="Seed of the returned mesh, one of the candidates' seed, "
                                               "seed+1, ...: that seed with candidates=1 gives this mesh alone.")
    result_from: Literal["model", "planes", "simplified", "decimated", "input"] | None = Field(
        None, description="Where the mesh comes from: generated by the networks (model), rebuilt from the input's "
                          "planes, the input mesh simplified within its flat faces, the input mesh's quadric "
                          "decimation to the same face count (nearer the input than the generated mesh), or the "
                          "input itself (already low-poly).")
    vertices_from: Literal["decoder", "quadrics", "planes", "simplified", "decimated", "input"] | None = Field(
        None, description="Where a generated mesh's vertices come from: the vertex decoder, or a mesh input's quadric "
                          "decimation (its corners and creases), connected by the face model; else as result_from.")
    quality: Quality | None = None
    placement: Placement | None = None
    notes: list[str] = Field(default_factory=list, description="What a format leaves out, for people: GLB holds "
                                                               "triangles and is Y-up; PLY holds no UVs; a bake "
                                                               "without a texture to read.")


class Timings(BaseModel):
    """Seconds.  ``queue``: created -> started (its last attempt); ``total``: the rest of the job, every second of
    it in one of the stages between: ``load`` (parsing the upload, and the worker reading it), the pipeline's
    (``encode``: reading the input and encoding it; ``vertices``; ``enhancer``; ``faces``: the face model, the
    triangles, rebuilds and the result finished and measured; ``filtering``: the masked re-predictions, 0 without
    filtering=true; ``weighing``: choosing among the candidates and the rival meshes), ``export`` (writing and
    storing the formats).  Null until known."""

    queue: float | None = None
    load: float | None = None
    encode: float | None = None
    vertices: float | None = None
    enhancer: float | None = None
    faces: float | None = None
    filtering: float | None = None
    weighing: float | None = None
    export: float | None = None
    total: float | None = None


class Webhook(BaseModel):
    """The job's ``callback_url`` and its deliveries (service.webhooks)."""

    url: str
    state: Literal["waiting", "retrying", "delivered", "failed"] = Field(
        description="waiting: the job is not finished (or its first delivery is under way); retrying: an attempt "
                    "failed and another is due at next_attempt_at; delivered: a 2xx answer; failed: every "
                    "attempt failed.")
    attempts: int = Field(description="Deliveries tried.")
    last_status: int | None = Field(description="HTTP status of the last attempt (null: no answer).")
    last_error: str | None = Field(description="Why the last attempt failed (null when it did not).")
    last_attempt_at: str | None
    next_attempt_at: str | None


class Job(BaseModel):
    id: str
    status: Status
    progress: Progress
    created_at: str | None
    started_at: str | None
    finished_at: str | None
    params: dict
    input: InputInfo
    result: ResultInfo | None
    timings: Timings
    error: ErrorDetail | None
    expires_at: str = Field(description="When the job, its input and its results are deleted: retention_seconds "
                                        "after it finished (or after it was created, while it has not finished).")
    webhook: Webhook | None = Field(description="Deliveries to the job's callback_url (null: none was given).")
    model_config = ConfigDict(json_schema_extra={"examples": [JOB_EXAMPLE]})


class JobPage(BaseModel):
    """One page of ``GET /v1/jobs``: the key's jobs, newest first."""

    jobs: list[Job]
    next_cursor: str | None = Field(description="Pass as ?cursor= for the next page; null on the last page.")


class Batch(BaseModel):
    """The jobs ``POST /v1/batches`` created, one per file, in the order of the files."""

    job_ids: list[str]
    jobs: list[Job]


class Health(BaseModel):
    status: str
    model_config = ConfigDict(json_schema_extra={"examples": [{"status": "ok"}]})


class Ready(BaseModel):
    status: str
    redis: bool
    workers: int
    queue_depth: int | None
    model_config = ConfigDict(json_schema_extra={
        "examples": [{"status": "ready", "redis": True, "workers": 1, "queue_depth": 0}]})


def error_responses(*codes: int) -> dict:
    """OpenAPI ``responses=`` entries for the error statuses a route can answer."""
    text = {400: "Bad request", 401: "Missing or unknown API key", 404: "No such job (for this key)",
            409: "Conflict with the job's state", 413: "Upload or input too large", 415: "Unsupported file type",
            422: "Invalid file or parameter", 429: "Queue full or rate limited (see Retry-After)",
            503: "Redis unreachable"}
    return {c: {"model": ErrorBody, "description": text.get(c, "Error")} for c in codes}
