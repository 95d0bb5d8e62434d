"""The jobs resource: ``/v1/jobs`` to submit a shape, ``/v1/jobs/{id}`` to watch, download, cancel or delete it.

Routes are thin: checks and answers here, state in :mod:`service.store`, the ``Idempotency-Key`` protocol in
:mod:`service.idempotency`, access (API key, rate limit, a job's owner) in :mod:`service.deps`.
"""

from __future__ import annotations

import threading
import time
from pathlib import PurePath
from typing import Literal
from urllib.parse import quote

import anyio
from fastapi import APIRouter, Depends, File, Form, Header, Query, Request, Response, UploadFile
from fastapi.responses import JSONResponse

from fastmesh.io import EXPORT_FORMATS
from fastmesh.output import MeshOut
from fastmesh.params import BOUNDS

from ..children import CappedPool, ChildFailed, ChildShapeError
from ..deps import JobId, Owner, StoreDep, owned_job
from ..errors import SHAPE_STATUS, ApiError
from ..forms import build_params, generation_defaults, safe_filename, strict_form
from ..idempotency import Idempotency
from ..listing import MAX_LIMIT, list_jobs
from ..parsing import parse_upload
from ..schemas import Job, JobPage, error_responses
from ..settings import Settings
from ..store import FINAL, STATUSES, QueueFull, Store
from ..submission import charge, parse_slot, read_upload, webhook_of

MEDIA = {"glb": "model/gltf-binary", "obj": "model/obj", "ply": "application/ply"}


def jobs_router(settings: Settings, parses: CappedPool,
                slots: threading.BoundedSemaphore | None = None) -> APIRouter:
    """The routes of one app.  They are built per ``settings`` because the OpenAPI schema shows them (the
    long-poll limit, the default formats) and the upload-parsing slots are counted per app; uploads are
    parsed in ``parses`` (``settings.max_concurrent_parses`` capped child processes) while holding one of
    ``slots`` (shared with ``POST /v1/batches``)."""
    router = APIRouter(prefix="/v1/jobs", tags=["jobs"])
    defaults = generation_defaults()
    parse_slots = slots or threading.BoundedSemaphore(settings.max_concurrent_parses)

    def d(name: str) -> str:
        return f"default {defaults.get(name)!r}"

    @router.post("", status_code=202, response_model=Job, summary="Submit a shape; returns the queued job",
                 dependencies=[Depends(strict_form)],
                 responses={**error_responses(401, 409, 413, 415, 422, 429, 503),
                            202: {"description": "Accepted; `Location` names the job",
                                  "headers": {"Location": {"schema": {"type": "string"}}}},
                            200: {"model": Job, "description": "A retry with the same Idempotency-Key: the job "
                                                               "that request created"}})
    def submit(request: Request, who: Owner, store: StoreDep,
               file: UploadFile = File(..., description="Mesh or point cloud; the extension names the format."),
               seed: int | None = Form(None, **BOUNDS["seed"].form_range(), description=f"Sampling seed ({d('seed')}).",
                                       examples=[0]),
               temperature: float | None = Form(None, allow_inf_nan=False,
                                                description=f"Sampling temperature ({d('temperature')}).",
                                                examples=[defaults.get("temperature")]),
               top_k: int | None = Form(None, **BOUNDS["top_k"].form_range(),
                                        description=f"Top-k sampling, 0 = off ({d('top_k')}).",
                                        examples=[defaults.get("top_k")]),
               top_p: float | None = Form(None, allow_inf_nan=False, description=f"Nucleus sampling ({d('top_p')}).",
                                          examples=[defaults.get("top_p")]),
               max_vertices: int | None = Form(None, **BOUNDS["max_vertices"].form_range(),
                                               description=f"Vertex budget; unset = the model's limit "
                                                           f"({d('max_vertices')}).",
                                               examples=[defaults.get("max_vertices")]),
               enhancer: bool | None = Form(None, description=f"Run the vertex enhancer ({d('enhancer')})."),
               filtering: bool | None = Form(None, description=f"Prediction filtering, masked re-predictions of "
                                                               f"the edges ({d('filtering')})."),
               candidates: int | None = Form(None, **BOUNDS["candidates"].form_range(),
                                             description="Meshes sampled (seeds seed, seed+1, ...); the one "
                                                         "nearest the input is returned; 1 is fastest "
                                                         f"({d('candidates')}).",
                                             examples=[defaults.get("candidates")]),
               target_faces: int | None = Form(None, **BOUNDS["target_faces"].form_range(),
                                               description="Faces to aim for, held within 20 % (result.quality "
                                                           "gives target_faces, faces and target_met); unset = the "
                                                           "model chooses the count from the shape.", examples=[300]),
               closed: Literal["auto", "true", "false"] | None = Form(
                   None, description="Close the result's holes: auto = when the input is closed (a closed mesh, or "
                                     f"oriented points that enclose a volume); the decision is in result.quality "
                                     f"({d('closed')}).", examples=["auto"]),
               topology: Literal["triangle", "quad"] | None = Form(
                   None, description="quad: pairs of triangles that make a near-planar, well-shaped quad become one, "
                                     "in the OBJ and PLY files (GLB holds triangles); result.quality.quad_share says "
                                     f"how many ({d('topology')}).", examples=["quad"]),
               uv: bool | None = Form(None, description="Give the result a UV layout (xatlas), in the GLB "
                                                        f"(TEXCOORD_0) and OBJ (vt) files ({d('uv')})."),
               bake: bool | None = Form(None, description="With uv: bake a textured glTF input's base colour onto "
                                                          f"the layout, into the GLB's texture ({d('bake')})."),
               origin: Literal["input", "center", "bottom"] | None = Form(
                   None, description="Where the result's origin lies: the input's own frame, its bounding box's "
                                     f"centre or its bottom centre (Y up) ({d('origin')}).", examples=["bottom"]),
               height: float | None = Form(None, allow_inf_nan=False, **BOUNDS["height"].form_range(),
                                           description="Scale the result to stand this many metres tall along Y "
                                                       "(unset: the input's size).", examples=[1.8]),
               up: Literal["y", "z"] | None = Form(None, description="Up axis of the OBJ and PLY files; GLB is always "
                                                                     f"Y-up, as glTF requires ({d('up')}).",
                                                   examples=["z"]),
               formats: str | None = Form(None, description="Comma list of glb, obj, ply exported with the job "
                                                            f"(default {','.join(settings.default_formats)}).",
                                          examples=["glb,obj"]),
               callback_url: str | None = Form(None, max_length=2000,
                                               description="https URL POSTed the job JSON, signed, when it "
                                                           "succeeds, fails or is cancelled (README, Webhooks).",
                                               examples=["https://example.com/fastmesh-hook"]),
               idempotency_key: str | None = Header(None, alias="Idempotency-Key", max_length=200,
                                                    description="Retrying with the same key returns the same job.")
               ) -> JSONResponse:
        charge(store, settings, request.state.bucket)
        params = build_params({"seed": seed, "temperature": temperature, "top_k": top_k, "top_p": top_p,
                               "max_vertices": max_vertices, "enhancer": enhancer, "filtering": filtering,
                               "candidates": candidates, "target_faces": target_faces, "closed": closed,
                               "topology": topology, "uv": uv, "bake": bake, "origin": origin, "height": height,
                               "up": up},
                              formats, settings.default_formats, store.vertex_limit())
        webhook = webhook_of(settings, callback_url)
        with parse_slot(parse_slots, settings):
            data = read_upload(file, settings)
            filename = safe_filename(file.filename)
            idem = Idempotency(store, who, idempotency_key, data,
                               {**params, "filename": filename, **({"callback_url": callback_url} if webhook else {})})
            existing = idem.existing()
            if existing is not None:
                return job_response(store, existing, 200)
            depth = store.queue_depth()
            if depth >= settings.max_queue_depth:
                raise queue_full(store, settings, depth)
            t0 = time.perf_counter()
            info, blob = parse(parses, settings, data, filename, texture=params["bake"])
            del data
            load_seconds = time.perf_counter() - t0
        job_id = store.new_id()
        existing = idem.claim(job_id)
        if existing is not None:
            return job_response(store, existing, 200)
        try:
            store.create(who, params, info, blob, load_seconds, max_queued=settings.max_queue_depth, job_id=job_id,
                         webhook=webhook)
        except BaseException as e:
            idem.release()
            if isinstance(e, QueueFull):  # the early check raced with concurrent submissions: the queue filled
                raise queue_full(store, settings, store.queue_depth()) from None
            raise
        idem.confirm(job_id)
        return job_response(store, store.get(job_id), 202)

    @router.get("", response_model=JobPage, summary="The key's jobs, newest first, a page at a time",
                responses=error_responses(401, 422, 429, 503))
    def get_jobs(who: Owner, store: StoreDep,
                 status: Literal[STATUSES] | None = Query(None, description="Only jobs in this status."),
                 limit: int = Query(20, ge=1, le=MAX_LIMIT, description="Most jobs on the page."),
                 cursor: str | None = Query(None, max_length=200, description="next_cursor of the page before.")
                 ) -> JSONResponse:
        return JSONResponse(list_jobs(store, who, status, limit, cursor))

    @router.get("/{job_id}", response_model=Job, summary="A job's status, progress, timings",
                responses={**error_responses(401, 404, 422, 429, 503),
                           200: {"headers": {"X-Queue-Position": {"description": "0-based, while queued",
                                                                  "schema": {"type": "integer"}}}}})
    def get_job(job_id: JobId, who: Owner, store: StoreDep) -> JSONResponse:
        return job_response(store, owned_job(store, job_id, who))

    @router.get("/{job_id}/result", summary="Download the mesh (input's original frame)", response_class=Response,
                responses={**error_responses(401, 404, 409, 422, 429, 503),
                           200: {"description": "The mesh file",
                                 "content": {m: {"schema": {"type": "string", "format": "binary"}}
                                             for m in MEDIA.values()}}})
    async def get_result(job_id: JobId, who: Owner, store: StoreDep,
                         format: str = Query("glb", pattern=f"^({'|'.join(EXPORT_FORMATS)})$",
                                             description="glb, obj or ply", examples=["glb"]),
                         wait: float = Query(0, ge=0, le=settings.max_wait_seconds,
                                             description="Seconds to wait for the job to finish (long poll).")
                         ) -> Response:
        job = await anyio.to_thread.run_sync(owned_job, store, job_id, who)
        deadline = time.monotonic() + wait
        step = 0.02  # short jobs answer fast; long waits settle at 5 Redis reads a second
        while job["status"] not in FINAL and time.monotonic() < deadline:
            await anyio.sleep(min(step, max(0.0, deadline - time.monotonic())))
            step = min(0.2, step * 1.5)
            job = await anyio.to_thread.run_sync(owned_job, store, job_id, who)
        if job["status"] in ("queued", "running"):
            raise ApiError(409, "not_ready", f"job is {job['status']}; poll GET /v1/jobs/{job_id} or add ?wait=",
                           {"Retry-After": "1"})
        if job["status"] != "succeeded":
            err = job.get("error") or {}
            raise ApiError(409, f"job_{job['status']}",
                           f"job {job['status']}, no result: {err.get('message', 'no detail')}")
        data = await anyio.to_thread.run_sync(result_bytes, store, job_id, format)
        stem = PurePath(job["input"]["filename"]).stem or "result"
        return Response(data, media_type=MEDIA[format], headers={"Content-Disposition": disposition(stem, format)})

    @router.delete("/{job_id}", summary="Cancel a queued/running job, or delete a finished one",
                   responses={**error_responses(401, 404, 422, 429, 503),
                              200: {"model": Job, "description": "Cancelled; the job as it is now"},
                              204: {"description": "Deleted with its input and results"}})
    def delete_job(job_id: JobId, who: Owner, store: StoreDep) -> Response:
        job = owned_job(store, job_id, who)
        if job["status"] in ("queued", "running") and store.cancel(job_id):
            return job_response(store, store.get(job_id))
        store.delete(job_id)
        return Response(status_code=204)

    return router


def parse(parses: CappedPool, settings: Settings, data: bytes, filename: str, texture: bool = False
          ) -> tuple[dict, bytes]:
    """``(input facts, stored input)`` of an upload, parsed in a capped child process (``texture``: with a glTF's
    base-colour texture, for ``bake``).

    Raises
    ------
    ApiError
        What the file is refused for: the ShapeError's code (413 ``too_large``, 415, 422); 413 ``too_large``
        when parsing needed more than ``child_memory_mb`` or ``parse_timeout_seconds``; 422 ``unreadable``
        when the parser's process died on it.
    """
    try:
        return parses.call(parse_upload, data, filename, settings.max_points, settings.max_faces, texture,
                           timeout=settings.parse_timeout_seconds)
    except ChildShapeError as e:
        raise ApiError(SHAPE_STATUS.get(e.code, 422), e.code, e.message) from None
    except ChildFailed as e:
        if e.reason == "memory":
            raise ApiError(413, "too_large", f"reading this file needs more than the {settings.child_memory_mb} "
                                             "MiB a parse may use (child_memory_mb); it declares or expands to "
                                             "too much data") from None
        if e.reason == "deadline":
            raise ApiError(413, "too_large", f"this file could not be read within {settings.parse_timeout_seconds:g}"
                                             " s (parse_timeout_seconds); it is too large or too complex") from None
        if e.reason == "busy":
            raise ApiError(429, "busy", "every parsing process is busy; retry shortly", {"Retry-After": "2"}) \
                from None
        raise ApiError(422, "unreadable", "the file could not be parsed: the parser stopped on it (it is damaged, "
                                          "or expands to more than can be read)") from None


def job_response(store: Store, job: dict, status: int = 200) -> JSONResponse:
    """The job as JSON, with ``Location`` and, while it is queued, ``X-Queue-Position``."""
    headers = {"Location": f"/v1/jobs/{job['id']}"}
    pos = store.queue_position(job)
    if pos is not None:
        headers["X-Queue-Position"] = str(pos)
    return JSONResponse(store.public(job), status_code=status, headers=headers)


def queue_full(store: Store, settings: Settings, depth: int) -> ApiError:
    """429 ``queue_full`` for ``depth`` queued jobs, with a ``Retry-After`` of about when a queue slot is likely
    free: the mean job time over the live workers, within [1, 600] seconds."""
    stats = store.stage_stats().get("total", {})
    mean = stats.get("sum", 0.0) / stats["count"] if stats.get("count") else 5.0
    workers = max(1, len(store.workers_alive()))
    retry = int(min(600, max(1, round(mean / workers))))
    return ApiError(429, "queue_full", f"{depth} jobs are waiting (limit {settings.max_queue_depth}); retry later",
                    {"Retry-After": str(retry)})


def result_bytes(store: Store, job_id: str, fmt: str) -> bytes:
    """The result in ``fmt``; a format not exported with the job is converted once and kept."""
    data = store.get_result(job_id, fmt)
    if data is not None:
        return data
    mesh = store.get_result(job_id, "npz")
    if mesh is None:
        raise ApiError(404, "not_found", "the result is no longer stored (retention expired or deleted)")
    data = MeshOut.from_npz(mesh).export(fmt)
    store.put_result(job_id, fmt, data, ttl=store.ttl_of(job_id))
    return data


def disposition(stem: str, ext: str) -> str:
    """``Content-Disposition`` of a download named after the upload: an ASCII ``filename`` for old clients and
    the name itself, UTF-8, as ``filename*`` (RFC 6266), which browsers prefer."""
    full = quote(f"{stem[:100]}.{ext}", safe="")
    return f'attachment; filename="{ascii_name(stem)}.{ext}"; filename*=UTF-8\'\'{full}'


def ascii_name(name: str) -> str:
    """``name`` safe inside a quoted Content-Disposition filename."""
    return "".join(c if c.isascii() and c.isprintable() and c not in '"\\' else "_" for c in name)[:100] or "result"
