"""The batches resource: ``POST /v1/batches`` submits several files with one set of parameters, a job each.

A batch is accepted whole or not at all: every file is read and parsed first, each as a single upload is;
a file refused is the batch's answer (its 4xx names the file by position and name) and no job is created.
A failure while creating the jobs (the queue filled meanwhile, Redis) deletes those already created.
The form is ``POST /v1/jobs``'s, with ``files`` (repeated, at most ``max_batch_files``) for ``file``.
An ``Idempotency-Key`` names the whole batch: a retry with the same files and parameters gets its jobs (200),
any difference (a file more or fewer included) is ``409 idempotency_conflict``.
"""

from __future__ import annotations

import contextlib

from fastapi import APIRouter, Depends, Request
from fastapi.responses import JSONResponse

from fastmesh_jobs.limits import QueueFull
from fastmesh_jobs.settings import Settings
from fastmesh_jobs.store import Store

from ..deps import Owner, Parses, ParseSlots, SettingsDep, StoreDep
from ..errors import ApiError
from ..forms import safe_filename, strict_form
from ..idempotency import Idempotency
from ..schemas import Batch, error_responses
from ..submission import charge, parse_slot, read_upload
from .form import BatchForm
from .jobs import create_once, fingerprinted, parse_timed, queue_full, submitted_params

router = APIRouter(prefix="/v1/batches", tags=["jobs"])

BATCH_CONFLICT = ("this Idempotency-Key was used for a different batch: other files, another number of files, "
                  "or other parameters")


@router.post("", status_code=202, response_model=Batch, dependencies=[Depends(strict_form)],
             summary="Submit several shapes with one set of parameters; returns their queued jobs",
             responses={**error_responses(401, 409, 413, 415, 422, 429, 503),
                        200: {"model": Batch, "description": "A retry with the same Idempotency-Key: the "
                                                             "jobs that request created"}})
def submit_batch(request: Request, who: Owner, store: StoreDep, settings: SettingsDep, parses: Parses,
                 slots: ParseSlots, form: BatchForm) -> JSONResponse:
    files = form.files
    if len(files) > settings.max_batch_files:
        raise ApiError(422, "too_many_files", f"files: {len(files)} sent; a batch takes at most "
                                              f"{settings.max_batch_files} (max_batch_files)")
    charge(store, settings, request.state.bucket, len(files))
    params, webhook = submitted_params(store, settings, form)
    depth = store.queue_depth()
    if depth + len(files) > settings.max_queue_depth:
        raise queue_full(store, settings, depth)
    fingerprint = fingerprinted(params, form, webhook)
    parsed = []
    for i, file in enumerate(files):
        filename = safe_filename(file.filename)
        with about_file(i, filename), parse_slot(slots, settings, request.state.bucket):
            data = read_upload(file, settings)
            key = f"{form.idempotency_key}#{i}" if form.idempotency_key else None
            # The number of files is part of each file's fingerprint: a retry with files added or left out
            # differs from the batch the key names (409), it does not extend or cut it.
            idem = Idempotency(store, who, key, data, {**fingerprint, "filename": filename, "batch_files": len(files)},
                               conflict=BATCH_CONFLICT)
            parsed.append((idem, parse_timed(parses, settings, data, filename, texture=params["bake"])))
            del data  # not held while the next file is read
    jobs_made = create_all(store, settings, who, params, webhook, parsed)
    status = 202 if any(made for _, made in jobs_made) else 200
    jobs_out = [store.public(job) for job, _ in jobs_made]
    return JSONResponse({"job_ids": [j["id"] for j in jobs_out], "jobs": jobs_out}, status_code=status)


@contextlib.contextmanager
def about_file(index: int, filename: str):
    """An ApiError raised in the block names the batch's file ``index``, ``filename``."""
    try:
        yield
    except ApiError as e:
        raise ApiError(e.status, e.code, f"files[{index}] '{filename}': {e.message}", e.headers) from None


def create_all(store: Store, settings: Settings, who: str, params: dict, webhook: dict | None,
               parsed: list[tuple[Idempotency, tuple[dict, bytes, float]]]) -> list[tuple[dict, bool]]:
    """Create a job per parsed file ``(idempotency, (input facts, stored input, load seconds))``: ``(job,
    created)`` each (created False: an Idempotency-Key's earlier job).  All or none: a failure deletes the jobs
    created before it."""
    done: list[tuple[dict, bool]] = []
    try:
        for idem, upload in parsed:
            existing = idem.existing()
            done.append((existing, False) if existing is not None else
                        create_once(store, settings, who, params, webhook, idem, upload))
    except BaseException as e:
        for (job, made), (idem, _) in zip(done, parsed, strict=False):  # done ends where creating failed
            if made:  # a worker that took it already stops at its next progress write, finding it gone
                if job.get("rq_id"):
                    store.queue.remove(job["rq_id"])
                store.delete(job["id"])
                idem.release()
        if isinstance(e, QueueFull):
            raise queue_full(store, settings, store.queue_depth()) from None
        raise
    return done
