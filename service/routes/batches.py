"""The batches resource: ``POST /v1/batches`` submits several files with one set of parameters, a job each.

A batch is accepted whole or not at all: every file is read and parsed first, each as a single upload is;
a file refused is the batch's answer (its 4xx names the file by position and name) and no job is created.
A failure while creating the jobs (the queue filled meanwhile, Redis) deletes those already created.
The form is ``POST /v1/jobs``'s, with ``files`` (repeated, at most ``max_batch_files``) for ``file``.
"""

from __future__ import annotations

import inspect
import threading
import time

from fastapi import APIRouter, Depends, File, UploadFile
from fastapi.responses import JSONResponse
from fastapi.routing import APIRoute

from ..children import CappedPool
from ..errors import ApiError
from ..forms import build_params, safe_filename, strict_form
from ..idempotency import Idempotency
from ..schemas import Batch, error_responses
from ..settings import Settings
from ..store import QueueFull, Store
from ..submission import charge, parse_slot, read_upload, webhook_of
from .jobs import parse, queue_full

# The submit route's parameters that are not generation parameters (everything else is handed to build_params).
NOT_GENERATION = ("request", "who", "store", "file", "files", "formats", "callback_url", "idempotency_key")


def batches_router(settings: Settings, parses: CappedPool, slots: threading.BoundedSemaphore,
                   jobs: APIRouter) -> APIRouter:
    """The batch route of one app; ``jobs`` is its jobs router, whose ``POST /v1/jobs`` form it takes."""
    router = APIRouter(prefix="/v1/batches", tags=["jobs"])

    def submit_batch(**form) -> JSONResponse:
        request, who, store = form["request"], form["who"], form["store"]
        files: list[UploadFile] = form["files"]
        if len(files) > settings.max_batch_files:
            raise ApiError(422, "too_many_files", f"files: {len(files)} sent; a batch takes at most "
                                                  f"{settings.max_batch_files} (max_batch_files)")
        charge(store, settings, request.state.bucket, len(files))
        params = build_params({k: v for k, v in form.items() if k not in NOT_GENERATION}, form["formats"],
                              settings.default_formats, store.vertex_limit())
        webhook = webhook_of(settings, form.get("callback_url"))
        depth = store.queue_depth()
        if depth + len(files) > settings.max_queue_depth:
            raise queue_full(store, settings, depth)
        fingerprinted = {**params, **({"callback_url": form["callback_url"]} if webhook else {})}
        parsed = [read_one(store, who, i, f, form.get("idempotency_key"), fingerprinted) for i, f in enumerate(files)]
        jobs_made = create_all(store, settings, who, params, webhook, parsed)
        status = 202 if any(made for _, made in jobs_made) else 200
        jobs_out = [store.public(job) for job, _ in jobs_made]
        return JSONResponse({"job_ids": [j["id"] for j in jobs_out], "jobs": jobs_out}, status_code=status)

    def read_one(store: Store, who: str, index: int, file: UploadFile, key: str | None, fingerprinted: dict):
        """``(idempotency, input facts, stored input, load seconds)`` of the batch's file ``index``; an ApiError
        about it names it."""
        filename = safe_filename(file.filename)
        try:
            with parse_slot(slots, settings):
                data = read_upload(file, settings)
                idem = Idempotency(store, who, f"{key}#{index}" if key else None, data,
                                   {**fingerprinted, "filename": filename})
                t0 = time.perf_counter()
                info, blob = parse(parses, settings, data, filename, texture=fingerprinted["bake"])
                return idem, info, blob, time.perf_counter() - t0
        except ApiError as e:
            raise ApiError(e.status, e.code, f"files[{index}] '{filename}': {e.message}", e.headers) from None

    # The submit route's signature with ``files`` for ``file``: FastAPI validates, converts and documents the
    # same fields here, so a generation field added to POST /v1/jobs is taken by batches too.
    submit = next(r.endpoint for r in jobs.routes
                  if isinstance(r, APIRoute) and r.path == jobs.prefix and "POST" in r.methods)
    sig = inspect.signature(submit, eval_str=True)
    files = inspect.Parameter("files", inspect.Parameter.POSITIONAL_OR_KEYWORD, annotation=list[UploadFile],
                              default=File(..., description="The shapes: repeat the field once per file."))
    submit_batch.__signature__ = sig.replace(
        parameters=[files if p.name == "file" else p for p in sig.parameters.values()],
        return_annotation=JSONResponse)
    router.post("", status_code=202, response_model=Batch, dependencies=[Depends(strict_form)],
                summary="Submit several shapes with one set of parameters; returns their queued jobs",
                responses={**error_responses(401, 409, 413, 415, 422, 429, 503),
                           200: {"model": Batch, "description": "A retry with the same Idempotency-Key: the "
                                                                "jobs that request created"}})(submit_batch)
    return router


def create_all(store: Store, settings: Settings, who: str, params: dict, webhook: dict | None,
               parsed: list[tuple]) -> list[tuple[dict, bool]]:
    """Create a job per parsed file: ``(job, created)`` each (created False: an Idempotency-Key's earlier job).
    All or none: a failure deletes the jobs created before it."""
    done: list[tuple[dict, bool]] = []
    try:
        for idem, info, blob, load_seconds in parsed:
            existing = idem.existing()
            if existing is not None:
                done.append((existing, False))
                continue
            job_id = store.new_id()
            existing = idem.claim(job_id)
            if existing is not None:
                done.append((existing, False))
                continue
            try:
                store.create(who, params, info, blob, load_seconds, max_queued=settings.max_queue_depth,
                             job_id=job_id, webhook=webhook)
            except BaseException:
                idem.release()
                raise
            idem.confirm(job_id)
            done.append((store.get(job_id), True))
    except BaseException as e:
        for (job, made), (idem, *_) in zip(done, parsed, strict=False):  # done ends where creating failed
            if made:  # a worker that took it already stops at its next progress write, finding it gone
                if job.get("rq_id"):
                    store.queue.remove(job["rq_id"])
                store.delete(job["id"])
                idem.release()
        if isinstance(e, QueueFull):
            raise queue_full(store, settings, store.queue_depth()) from None
        raise
    return done
