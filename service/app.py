"""The HTTP API: upload a shape, poll the job, download the artist mesh.

``create_app(settings)`` builds the app; ``uvicorn service.app:create_app --factory`` serves it with
settings from the environment.  Routes are thin: checks and answers here, state in :mod:`service.store`.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import logging
import re
import threading
import time
from contextlib import asynccontextmanager
from pathlib import PurePath

import anyio
from fastapi import Depends, FastAPI, File, Form, Header, Path, Query, Request, Response, UploadFile
from fastapi.responses import JSONResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from fastmesh.io import EXPORT_FORMATS, ShapeError, export_mesh, load_shape
from fastmesh.params import MAX_CANDIDATES, TARGET_FACES

from . import errors
from .errors import ApiError
from .metrics import Metrics
from .middleware import ApiKeyGate, BodyLimit, JsonCORS, RequestMetrics
from .params import build_params, generation_defaults, input_info, safe_filename
from .preview import DEFAULT_PREVIEW, preview_router
from .render_pool import RenderPool
from .schemas import Health, Job, Ready, error_responses
from .settings import Settings
from .store import FINAL, QueueFull, Store, mesh_from_bytes, shape_to_bytes
from .web.routes import web_router

log = logging.getLogger("fastmesh.service")

JOB_ID = Path(..., description="Job id as returned by POST /v1/jobs.",
              examples=["3f2b9c1d4e5f40718293a4b5c6d7e8f9"])
ID_RE = re.compile(r"[0-9a-f]{32}")
MEDIA = {"glb": "model/gltf-binary", "obj": "model/obj", "ply": "application/ply"}
IDEMPOTENCY_WAIT = 5.0  # seconds a retry waits for the job of a request holding the same Idempotency-Key
DESCRIPTION = """Upload a point cloud or a dense mesh, poll the job, download a clean artist-style mesh.

1. `POST /v1/jobs` with a multipart `file` (obj, glb, gltf, ply, stl, off, xyz, txt, npy, npz) -> 202 + job.
2. `GET /v1/jobs/{id}` until `status` is `succeeded` (or `failed` / `cancelled`).
3. `GET /v1/jobs/{id}/result?format=glb` (add `&wait=60` to long-poll instead of step 2).

When the server has API keys, send `Authorization: Bearer <key>`; a key sees only its own jobs.
Every error is JSON `{"error": {"code", "message"}}`."""


def create_app(settings: Settings | None = None, store: Store | None = None) -> FastAPI:
    settings = settings or Settings()
    store = store or Store(settings)
    metrics = Metrics(store)
    defaults = generation_defaults()
    renders = RenderPool(DEFAULT_PREVIEW.max_concurrent_renders)
    parse_slots = threading.BoundedSemaphore(settings.max_concurrent_parses)
    keys = {hashlib.sha256(k.encode()).hexdigest()[:16]: k for k in settings.api_keys}
    # Documents the scheme in OpenAPI (the /docs "Authorize" button); checking is ours, for JSON errors.
    bearer = HTTPBearer(auto_error=False, description="An API key from FASTMESH_API_KEYS (when set).")

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        stop = threading.Event()
        reaper = threading.Thread(target=_reap_loop, args=(store, stop), name="fastmesh-reaper", daemon=True)
        reaper.start()
        yield
        stop.set()
        renders.close()

    app = FastAPI(title="FastMesh", version="0.1.0", description=DESCRIPTION, lifespan=lifespan,
                  openapi_tags=[{"name": "jobs", "description": "Submit, watch, download, cancel."},
                                {"name": "ops", "description": "Health, readiness, metrics."}])
    app.state.settings, app.state.store, app.state.metrics = settings, store, metrics
    errors.install(app)

    # ------------------------------------------------------------------ access
    def key_of(token: str) -> str | None:
        """The hash naming the key ``token`` is, None when it is none of them."""
        token = token.strip().encode()
        return next((h for h, k in keys.items() if hmac.compare_digest(token, k.encode())), None)

    def owner(request: Request, cred: HTTPAuthorizationCredentials | None = Depends(bearer)) -> str:
        """Who is asking: the hash of their API key, or 'anonymous' when keys are off.  Rate-limits them."""
        if keys:
            who = key_of(cred.credentials if cred else "")
            if who is None:
                raise ApiError(401, "unauthorized", "missing or unknown API key; send 'Authorization: Bearer <key>'",
                               {"WWW-Authenticate": "Bearer"})
            bucket = who
        else:
            who = "anonymous"
            bucket = request.client.host if request.client else "anonymous"
        wait = store.rate_hit("req", bucket, settings.rate_limit_per_minute)
        if wait:
            raise ApiError(429, "rate_limited",
                           f"more than {settings.rate_limit_per_minute} requests per minute for this key",
                           {"Retry-After": str(wait)})
        request.state.bucket = bucket
        return who

    def job_of(job_id: str, who: str) -> dict:
        job = store.get(job_id) if ID_RE.fullmatch(job_id) else None
        if job is None or job["owner"] != who:  # another key's job is indistinguishable from no job
            raise ApiError(404, "not_found", f"no job '{job_id[:64]}'")
        return job

    def job_response(job: dict, status: int = 200) -> JSONResponse:
        headers = {"Location": f"/v1/jobs/{job['id']}"}
        pos = store.queue_position(job)
        if pos is not None:
            headers["X-Queue-Position"] = str(pos)
        return JSONResponse(store.public(job), status_code=status, headers=headers)

    # Routers added to this app (previews, the web page) reuse the same access rules.
    app.state.owner, app.state.job_of = owner, job_of

    # ------------------------------------------------------------------ jobs
    def d(name: str) -> str:
        return f"default {defaults.get(name)!r}"

    @app.post("/v1/jobs", tags=["jobs"], status_code=202, response_model=Job,
              summary="Submit a shape; returns the queued job",
              responses={**error_responses(401, 409, 413, 415, 422, 429, 503),
                         202: {"description": "Accepted; `Location` names the job",
                               "headers": {"Location": {"schema": {"type": "string"}}}},
                         200: {"model": Job, "description": "A retry with the same Idempotency-Key: the job "
                                                            "that request created"}})
    def submit(request: Request,
               file: UploadFile = File(..., description="Mesh or point cloud; the extension names the format."),
               seed: int | None = Form(None, ge=0, le=2**32 - 1, description=f"Sampling seed ({d('seed')}).",
                                       examples=[0]),
               temperature: float | None = Form(None, allow_inf_nan=False,
                                                description=f"Sampling temperature ({d('temperature')}).",
                                                examples=[defaults.get("temperature")]),
               top_k: int | None = Form(None, ge=0, le=1_000_000,
                                        description=f"Top-k sampling, 0 = off ({d('top_k')}).",
                                        examples=[defaults.get("top_k")]),
               top_p: float | None = Form(None, allow_inf_nan=False, description=f"Nucleus sampling ({d('top_p')}).",
                                          examples=[defaults.get("top_p")]),
               max_vertices: int | None = Form(None, ge=3, le=1_000_000,
                                               description=f"Vertex budget; unset = the model's limit "
                                                           f"({d('max_vertices')}).",
                                               examples=[defaults.get("max_vertices")]),
               enhancer: bool | None = Form(None, description=f"Run the vertex enhancer ({d('enhancer')})."),
               filtering: bool | None = Form(None, description=f"Filter bad faces ({d('filtering')})."),
               candidates: int | None = Form(None, ge=1, le=MAX_CANDIDATES,
                                             description="Meshes sampled (seeds seed, seed+1, ...); the one "
                                                         "nearest the input is returned; 1 is fastest "
                                                         f"({d('candidates')}).",
                                             examples=[defaults.get("candidates")]),
               target_faces: int | None = Form(None, ge=TARGET_FACES[0], le=TARGET_FACES[1],
                                               description="Faces to aim for; unset = the model chooses the count "
                                                           "from the shape.", examples=[300]),
               formats: str | None = Form(None, description="Comma list of glb, obj, ply exported with the job "
                                                            f"(default {','.join(settings.default_formats)}).",
                                          examples=["glb,obj"]),
               idempotency_key: str | None = Header(None, alias="Idempotency-Key", max_length=200,
                                                    description="Retrying with the same key returns the same job."),
               who: str = Depends(owner)) -> JSONResponse:
        wait = store.rate_hit("submit", request.state.bucket, settings.submit_rate_limit_per_minute)
        if wait:
            raise ApiError(429, "rate_limited", f"more than {settings.submit_rate_limit_per_minute} submissions "
                                                "per minute for this key", {"Retry-After": str(wait)})
        params = build_params({"seed": seed, "temperature": temperature, "top_k": top_k, "top_p": top_p,
                               "max_vertices": max_vertices, "enhancer": enhancer, "filtering": filtering,
                               "candidates": candidates, "target_faces": target_faces},
                              formats, settings.default_formats, store.vertex_limit())
        # Reading and parsing hold up to a few times the upload in memory: a fixed number at once keeps the
        # API's peak a known multiple of the limits; beyond it the client is told to come back.
        if not parse_slots.acquire(timeout=settings.parse_wait_seconds):
            raise ApiError(429, "busy", f"{settings.max_concurrent_parses} uploads are being read; retry shortly",
                           {"Retry-After": "2"})
        try:
            data = file.file.read(settings.max_upload_bytes + 1)
            if len(data) > settings.max_upload_bytes:
                raise ApiError(413, "too_large", f"upload larger than the {settings.max_upload_bytes} byte limit")
            filename = safe_filename(file.filename)
            fingerprint = hashlib.sha256(data + json.dumps(params, sort_keys=True).encode()).hexdigest()[:32]
            if idempotency_key:
                existing = _idempotent_job(store, who, idempotency_key, fingerprint)
                if existing is not None:
                    return job_response(existing, 200)
            depth = store.queue_depth()
            if depth >= settings.max_queue_depth:
                raise ApiError(429, "queue_full", f"{depth} jobs are waiting (limit {settings.max_queue_depth}); "
                                                  "retry later", {"Retry-After": str(_retry_after(store, depth))})
            t0 = time.perf_counter()
            try:
                # A point cloud's normals are estimated by the worker, outside the request path.
                shape = load_shape(data, filename=filename, max_points=settings.max_points,
                                   max_faces=settings.max_faces, normals=False)
            except ShapeError as e:
                raise ApiError(errors.SHAPE_STATUS.get(e.code, 422), e.code, e.message) from None
            del data
            load_seconds = time.perf_counter() - t0
            info = input_info(filename, shape)
            blob = shape_to_bytes(shape)
            del shape
        finally:
            parse_slots.release()
        job_id = store.new_id()
        if idempotency_key:
            # The claim names the job id before the job exists: an API killed between creating the job
            # and answering leaves a key that a retry resolves to that job, not a second one.
            claim = f"{job_id} {fingerprint} pending"
            if store.idempotency_claim(who, idempotency_key, claim) is not None:
                # Another request holds the key: answer with its job once it exists.  A claim that
                # expires meanwhile (its API process died before creating the job) is ours to take.
                existing = _idempotent_job(store, who, idempotency_key, fingerprint, wait=IDEMPOTENCY_WAIT)
                if existing is not None:
                    return job_response(existing, 200)
                if store.idempotency_claim(who, idempotency_key, claim) is not None:
                    raise ApiError(409, "conflict", "a request with this Idempotency-Key is still being processed",
                                   {"Retry-After": "1"})
        try:
            store.create(who, params, info, blob, load_seconds, max_queued=settings.max_queue_depth, job_id=job_id)
        except QueueFull:  # the early check above raced with concurrent submissions: the queue filled meanwhile
            if idempotency_key:
                store.idempotency_release(who, idempotency_key)
            depth = store.queue_depth()
            raise ApiError(429, "queue_full", f"{depth} jobs are waiting (limit {settings.max_queue_depth}); "
                                              "retry later", {"Retry-After": str(_retry_after(store, depth))}) from None
        except BaseException:
            if idempotency_key:
                store.idempotency_release(who, idempotency_key)
            raise
        if idempotency_key:
            store.idempotency_replace(who, idempotency_key, claim, f"{job_id} {fingerprint}")
        return job_response(store.get(job_id), 202)

    @app.get("/v1/jobs/{job_id}", tags=["jobs"], response_model=Job, summary="A job's status, progress, timings",
             responses={**error_responses(401, 404, 422, 429, 503),
                        200: {"headers": {"X-Queue-Position": {"description": "0-based, while queued",
                                                               "schema": {"type": "integer"}}}}})
    def get_job(job_id: str = JOB_ID, who: str = Depends(owner)) -> JSONResponse:
        return job_response(job_of(job_id, who))

    @app.get("/v1/jobs/{job_id}/result", tags=["jobs"], summary="Download the mesh (input's original frame)",
             response_class=Response,
             responses={**error_responses(401, 404, 409, 422, 429, 503),
                        200: {"description": "The mesh file",
                              "content": {m: {"schema": {"type": "string", "format": "binary"}}
                                          for m in MEDIA.values()}}})
    async def get_result(job_id: str = JOB_ID,
                         format: str = Query("glb", pattern=f"^({'|'.join(EXPORT_FORMATS)})$",
                                             description="glb, obj or ply", examples=["glb"]),
                         wait: float = Query(0, ge=0, le=settings.max_wait_seconds,
                                             description="Seconds to wait for the job to finish (long poll)."),
                         who: str = Depends(owner)) -> Response:
        job = await anyio.to_thread.run_sync(job_of, job_id, who)
        deadline = time.monotonic() + wait
        step = 0.02  # short jobs answer fast; long waits settle at 5 Redis reads a second
        while job["status"] not in FINAL and time.monotonic() < deadline:
            await anyio.sleep(min(step, max(0.0, deadline - time.monotonic())))
            step = min(0.2, step * 1.5)
            job = await anyio.to_thread.run_sync(job_of, job_id, who)
        if job["status"] in ("queued", "running"):
            raise ApiError(409, "not_ready", f"job is {job['status']}; poll GET /v1/jobs/{job_id} or add ?wait=",
                           {"Retry-After": "1"})
        if job["status"] != "succeeded":
            err = job.get("error") or {}
            raise ApiError(409, f"job_{job['status']}",
                           f"job {job['status']}, no result: {err.get('message', 'no detail')}")
        data = await anyio.to_thread.run_sync(_result_bytes, store, job_id, format)
        stem = PurePath(job["input"]["filename"]).stem or "result"
        return Response(data, media_type=MEDIA[format],
                        headers={"Content-Disposition": f'attachment; filename="{_ascii(stem)}.{format}"'})

    @app.delete("/v1/jobs/{job_id}", tags=["jobs"], summary="Cancel a queued/running job, or delete a finished one",
                responses={**error_responses(401, 404, 422, 429, 503),
                           200: {"model": Job, "description": "Cancelled; the job as it is now"},
                           204: {"description": "Deleted with its input and results"}})
    def delete_job(job_id: str = JOB_ID, who: str = Depends(owner)) -> Response:
        job = job_of(job_id, who)
        if job["status"] in ("queued", "running") and store.cancel(job_id):
            return job_response(store.get(job_id))
        store.delete(job_id)
        return Response(status_code=204)

    # ------------------------------------------------------------------ ops
    @app.get("/healthz", tags=["ops"], response_model=Health, summary="The process is up")
    async def healthz() -> dict:  # async: answers from the event loop even when every worker thread is busy
        return {"status": "ok"}

    @app.get("/readyz", tags=["ops"], response_model=Ready, summary="Redis reachable and a worker alive",
             responses=error_responses(503))
    def readyz() -> dict:
        try:
            store.r.ping()
            workers, depth = len(store.workers_alive()), store.queue_depth()
        except Exception as e:
            raise ApiError(503, "not_ready", f"Redis unreachable: {type(e).__name__}") from None
        if workers == 0:
            raise ApiError(503, "not_ready", "Redis reachable but no worker alive")
        return {"status": "ready", "redis": True, "workers": workers, "queue_depth": depth}

    @app.get("/metrics", tags=["ops"], summary="Prometheus metrics", response_class=Response,
             responses={200: {"content": {"text/plain": {"example": "fastmesh_queue_depth 0.0\n"}}}})
    def prometheus() -> Response:
        return Response(metrics.render(), media_type="text/plain; version=0.0.4; charset=utf-8")

    app.state.previews = preview_router(store, owner, job_of, renders)
    app.include_router(app.state.previews)  # /v1/jobs/{id}/preview.png, .../input.ply
    app.include_router(web_router(settings, defaults))  # the page at / (service/web)

    # Each add_middleware wraps the previous ones: CORS ends outermost, so 413s and 429s carry its headers too.
    app.add_middleware(BodyLimit, max_bytes=settings.max_upload_bytes, idle_seconds=settings.body_timeout_seconds)
    if keys:
        app.add_middleware(ApiKeyGate, known=lambda token: key_of(token) is not None,
                           fail_hit=lambda a: store.rate_hit("authfail", a, settings.auth_fail_limit_per_minute),
                           fail_wait=lambda a: store.rate_wait("authfail", a, settings.auth_fail_limit_per_minute))
    app.add_middleware(RequestMetrics, metrics=metrics)
    if settings.cors_origins:
        app.add_middleware(JsonCORS, allow_origins=settings.cors_origins,
                           allow_methods=["GET", "POST", "DELETE"],
                           allow_headers=["Authorization", "Idempotency-Key", "Content-Type"],
                           expose_headers=["Location", "Retry-After", "X-Queue-Position"])
    return app


def _idempotent_job(store: Store, who: str, key: str, fingerprint: str, wait: float = 0.0) -> dict | None:
    """The job an Idempotency-Key already names (same request), None if unclaimed; 409 for another request.

    A claim still marked pending whose job does not exist yet belongs to a request in flight (or to
    an API process killed before creating the job: the claim then expires after ``PENDING_TTL``);
    this waits up to ``wait`` seconds for its job to appear.
    """
    deadline = time.monotonic() + wait
    while True:
        raw = store.idempotency_get(who, key)
        if raw is None:
            return None
        job_id, fp, *pending = raw.split(" ")
        job = store.get(job_id)
        if (job is None or job["owner"] != who) and not pending:
            store.idempotency_release(who, key)  # its job was deleted or expired: the key is free again
            return None
        if fp != fingerprint:
            raise ApiError(409, "idempotency_conflict",
                           "this Idempotency-Key was used for a different file or parameters")
        if job is not None and job["owner"] == who:
            return job
        if time.monotonic() >= deadline:
            return None
        time.sleep(0.05)


def _retry_after(store: Store, depth: int) -> int:
    """Seconds until a queue slot is likely free: mean job time / live workers, within [1, 600]."""
    stats = store.stage_stats().get("total", {})
    mean = stats.get("sum", 0.0) / stats["count"] if stats.get("count") else 5.0
    workers = max(1, len(store.workers_alive()))
    return int(min(600, max(1, round(mean / workers))))


def _result_bytes(store: Store, job_id: str, fmt: str) -> bytes:
    data = store.get_result(job_id, fmt)
    if data is not None:
        return data
    mesh = store.get_result(job_id, "npz")
    if mesh is None:
        raise ApiError(404, "not_found", "the result is no longer stored (retention expired or deleted)")
    data = export_mesh(*mesh_from_bytes(mesh), fmt)  # a format not exported with the job: convert once, keep
    store.put_result(job_id, fmt, data, ttl=store.ttl_of(job_id))
    return data


def _ascii(name: str) -> str:
    return "".join(c if c.isascii() and c.isprintable() and c not in '"\\' else "_" for c in name)[:100] or "result"


def _reap_loop(store: Store, stop: threading.Event) -> None:
    """Requeue jobs of dead workers even when no worker is alive to notice."""
    while not stop.wait(store.settings.reaper_interval):
        try:
            for job_id, action in store.reap():
                log.warning("reaper: job %s %s", job_id, action)
        except Exception as e:  # Redis down: try again next tick
            log.warning("reaper: %s", e)
