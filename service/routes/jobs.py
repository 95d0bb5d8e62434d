"""The jobs resource: ``/v1/jobs`` to submit a shape, ``/v1/jobs/{id}`` to watch, download, cancel or delete it.

Routes are thin: checks and answers here, the form in :mod:`.form`, state in :mod:`fastmesh_jobs.store`, the
``Idempotency-Key`` protocol in :mod:`service.idempotency`, access (API key, rate limit, a job's owner) and the
app's objects in :mod:`service.deps`.
"""

from __future__ import annotations

import functools
import time
from pathlib import PurePath
from typing import Annotated, Literal
from urllib.parse import quote

import anyio
from fastapi import APIRouter, Depends, Query, Request, Response
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import Field, TypeAdapter, ValidationError

from fastmesh.export.output import MeshOut
from fastmesh.shapes.shape import EXPORT_FORMATS
from fastmesh_jobs.limits import QueueFull
from fastmesh_jobs.settings import Settings
from fastmesh_jobs.states import FINAL, STATUSES
from fastmesh_jobs.store import Store

from ..children import CappedPool, ChildFailed, ChildShapeError
from ..deps import JobId, Owner, Parses, ParseSlots, SettingsDep, StoreDep, owned_job
from ..errors import SHAPE_STATUS, ApiError
from ..forms import build_params, safe_filename, strict_form
from ..idempotency import Idempotency
from ..listing import MAX_LIMIT, list_jobs
from ..parsing import parse_upload
from ..schemas import Job, JobPage, error_responses
from ..submission import charge, parse_slot, read_upload, webhook_of
from .form import JobForm, Submission, formats_description

MEDIA = {"glb": "model/gltf-binary", "obj": "model/obj", "ply": "application/ply"}

router = APIRouter(prefix="/v1/jobs", tags=["jobs"])


@router.post("", status_code=202, response_model=Job, summary="Submit a shape; returns the queued job",
             dependencies=[Depends(strict_form)],
             responses={**error_responses(401, 409, 413, 415, 422, 429, 503),
                        202: {"description": "Accepted; `Location` names the job",
                              "headers": {"Location": {"schema": {"type": "string"}}}},
                        200: {"model": Job, "description": "A retry with the same Idempotency-Key: the job "
                                                           "that request created"}})
def submit(request: Request, who: Owner, store: StoreDep, settings: SettingsDep, parses: Parses,
           slots: ParseSlots, form: JobForm) -> JSONResponse:
    charge(store, settings, request.state.bucket)
    params, webhook = submitted_params(store, settings, form)
    (file,) = form.files
    with parse_slot(slots, settings, request.state.bucket):
        data = read_upload(file, settings)
        filename = safe_filename(file.filename)
        idem = Idempotency(store, who, form.idempotency_key, data,
                           {**fingerprinted(params, form, webhook), "filename": filename})
        existing = idem.existing()
        if existing is not None:
            return job_response(store, existing, 200)
        depth = store.queue_depth()
        if depth >= settings.max_queue_depth:
            raise queue_full(store, settings, depth)
        parsed = parse_timed(parses, settings, data, filename, texture=params["bake"])
        del data
    try:
        job, made = create_once(store, settings, who, params, webhook, idem, parsed)
    except QueueFull:  # the early check raced with concurrent submissions: the queue filled
        raise queue_full(store, settings, store.queue_depth()) from None
    return job_response(store, job, 202 if made else 200)


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


# ``wait``'s range is the app's (``settings.max_wait_seconds``): checked by :func:`long_poll_seconds`, stated in
# each app's schema by :func:`document_settings`.
Wait = Annotated[float, Query(description="Seconds to wait for the job to finish (long poll).")]


@router.get("/{job_id}/result", summary="Download the mesh (input's original frame)", response_class=Response,
            responses={**error_responses(401, 404, 409, 422, 429, 503),
                       200: {"description": "The mesh file",
                             "content": {m: {"schema": {"type": "string", "format": "binary"}}
                                         for m in MEDIA.values()}}})
async def get_result(job_id: JobId, who: Owner, store: StoreDep, settings: SettingsDep,
                     format: str = Query("glb", pattern=f"^({'|'.join(EXPORT_FORMATS)})$",
                                         description="glb, obj or ply", examples=["glb"]),
                     wait: Wait = 0) -> Response:
    wait = long_poll_seconds(wait, settings.max_wait_seconds)
    job = await finished_job(store, job_id, who, wait)
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


def submitted_params(store: Store, settings: Settings, form: Submission) -> tuple[dict, dict | None]:
    """``(params, webhook)`` of a submission: its generation parameters validated, with the export formats, and
    the ``webhook`` field of its jobs (None without ``callback_url``).

    Raises
    ------
    ApiError
        422 naming the field refused.
    """
    params = build_params(form.fields.generation, form.fields.formats, settings.default_formats,
                          store.vertex_limit())
    return params, webhook_of(settings, form.fields.callback_url)


def fingerprinted(params: dict, form: Submission, webhook: dict | None) -> dict:
    """What an ``Idempotency-Key`` retry must repeat, besides the upload and its name."""
    return {**params, **({"callback_url": form.fields.callback_url} if webhook else {})}


def create_once(store: Store, settings: Settings, who: str, params: dict, webhook: dict | None, idem: Idempotency,
                parsed: tuple[dict, bytes, float]) -> tuple[dict, bool]:
    """``(job, True)``: the job of the parsed upload ``(input facts, stored input, load seconds)``, created now;
    ``(job, False)``: the job a request holding the same ``Idempotency-Key`` made meanwhile.

    Raises
    ------
    QueueFull
        The queue filled since it was checked (the key is released).
    """
    job_id = store.new_id()
    existing = idem.claim(job_id)
    if existing is not None:
        return existing, False
    info, blob, load_seconds = parsed
    try:
        store.create(who, params, info, blob, load_seconds, max_queued=settings.max_queue_depth, job_id=job_id,
                     webhook=webhook)
    except BaseException:
        idem.release()
        raise
    idem.confirm(job_id)
    return store.get(job_id), True


@functools.lru_cache(maxsize=16)
def _wait_range(limit: float) -> TypeAdapter:
    return TypeAdapter(Annotated[float, Field(ge=0, le=limit)])


def long_poll_seconds(wait: float, limit: float) -> float:
    """``wait`` when it lies in [0, ``limit``].

    Raises
    ------
    RequestValidationError
        Outside, with pydantic's own message, as for a range declared on the query parameter.
    """
    try:
        return _wait_range(limit).validate_python(wait)
    except ValidationError as e:
        raise RequestValidationError([{**err, "loc": ("query", "wait")} for err in e.errors()]) from None


async def finished_job(store: Store, job_id: str, who: str, wait: float) -> dict:
    """The job once it is final, or as it is after ``wait`` seconds."""
    job = await anyio.to_thread.run_sync(owned_job, store, job_id, who)
    deadline = time.monotonic() + wait
    step = 0.02  # short jobs answer fast; long waits settle at 5 Redis reads a second
    while job["status"] not in FINAL and time.monotonic() < deadline:
        await anyio.sleep(min(step, max(0.0, deadline - time.monotonic())))
        step = min(0.2, step * 1.5)
        job = await anyio.to_thread.run_sync(owned_job, store, job_id, who)
    return job


def document_settings(schema: dict, settings: Settings) -> dict:
    """``schema`` (the app's OpenAPI, changed in place) stating what these routes take from ``settings``: the
    range of the long poll's ``wait`` and the formats exported when a submission names none."""
    for param in schema["paths"]["/v1/jobs/{job_id}/result"]["get"]["parameters"]:
        if param["name"] == "wait":  # placed as pydantic places a declared range
            param["schema"] = {"type": "number", "maximum": settings.max_wait_seconds, "minimum": 0,
                               **param["schema"]}
    for name, body in schema["components"]["schemas"].items():
        if name.startswith("Body_") and "formats" in body["properties"]:
            body["properties"]["formats"]["description"] = formats_description(settings.default_formats)
    return schema


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


def parse_timed(parses: CappedPool, settings: Settings, data: bytes, filename: str, texture: bool = False
                ) -> tuple[dict, bytes, float]:
    """:func:`parse`'s ``(input facts, stored input)`` and the seconds it took."""
    t0 = time.perf_counter()
    info, blob = parse(parses, settings, data, filename, texture)
    return info, blob, time.perf_counter() - t0


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
