"""What a worker does with one job: the function RQ calls, and the per-process model cache.

RQ carries only ``(job id, attempt)``.  The job's input, parameters and state live in Redis
(:mod:`fastmesh_jobs.store`), so a worker on another machine needs nothing but the Redis URL.
"""

from __future__ import annotations

import dataclasses
import gc
import logging
import os
import socket
import sys
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import redis
from rq.timeouts import JobTimeoutException

from fastmesh.shapes.io import ready_cloud
from fastmesh.shapes.shape import ShapeError
from fastmesh_jobs.blobs import mesh_to_bytes, shape_from_bytes
from fastmesh_jobs.memory import trim_malloc, tune_malloc
from fastmesh_jobs.runtime import wait_for
from fastmesh_jobs.settings import Settings
from fastmesh_jobs.states import timeout_error
from fastmesh_jobs.store import Store

log = logging.getLogger("fastmesh.worker")


class _State:
    """Per-process: the loaded pipeline (once per process, never per job) and what is running now."""

    def __init__(self):
        self.settings: Settings | None = None
        self.store: Store | None = None
        self.name = f"fastmesh-{socket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex[:4]}"
        self.pipeline = None
        self.loads = 0           # how many times this process built a Pipeline (the tests expect 1)
        self.jobs = 0
        self.running: dict[str, int] = {}   # job id -> attempt of the jobs running now, read by the heartbeat thread
        self.shutting_down = False
        # Set once a job met an error of the accelerator: the process takes no further job (worker.main).
        self.device_failed = False
        self.lock = threading.Lock()
        self.max_batch = 1  # jobs decoded together (worker.batch); set by worker.main

    def configure(self, settings: Settings, store: Store | None = None) -> None:
        self.settings, self.store = settings, store or Store(settings)

    def ensure(self) -> None:
        if self.store is None:  # run by a plain `rq worker`: settings from the environment
            self.configure(Settings())
        with self.lock:
            if self.pipeline is None:
                tune_malloc(arenas=None)  # before the model's and the jobs' allocations: large blocks given back
                self.pipeline = load_pipeline(self.settings)
                self.loads += 1

    def info(self) -> dict:
        s = self.settings
        limit = getattr(self.pipeline, "max_vertices", None)
        return {"pid": os.getpid(), "host": socket.gethostname(), "loads": self.loads, "jobs": self.jobs,
                "max_vertices": limit,
                "weights": s.weights or "shipped", "device": s.device or "auto",
                "current": [[j, a] for j, a in list(self.running.items())], "max_batch": self.max_batch}


STATE = _State()

# What torch's messages say when the accelerator itself failed.  After a device-side assert or an illegal
# memory access the process's CUDA context is unusable: every later kernel launch fails the same way, so
# the only cure is a fresh process.  (Out of memory is not one of them: the context survives it.)
DEVICE_ERROR_MARKERS = ("CUDA error", "CUDA driver error", "device-side assert", "CUBLAS_STATUS", "CUDNN_STATUS",
                        "cuDNN error", "illegal memory access", "unspecified launch failure", "HIP error")


def is_device_error(error: BaseException) -> bool:
    """Whether ``error`` (or an exception it was raised from) is a failure of the accelerator (CUDA/ROCm).

    Parameters
    ----------
    error : BaseException
        What a job raised.

    Returns
    -------
    bool
        True for ``torch.AcceleratorError`` and for RuntimeErrors whose message carries one of
        :data:`DEVICE_ERROR_MARKERS`; False for out-of-memory errors and for the pipeline's own errors.
    """
    torch = sys.modules.get("torch")  # imported by the pipeline whenever a device error is possible
    accelerator = getattr(torch, "AcceleratorError", None)
    out_of_memory = getattr(torch, "OutOfMemoryError", None)
    seen = set()
    while error is not None and id(error) not in seen:
        seen.add(id(error))
        if out_of_memory is not None and isinstance(error, out_of_memory):
            return False
        if accelerator is not None and isinstance(error, accelerator):
            return True
        if isinstance(error, RuntimeError) and not hasattr(error, "code"):
            if any(m in str(error) for m in DEVICE_ERROR_MARKERS):
                return True
        error = error.__cause__ or error.__context__
    return False


def load_pipeline(settings: Settings):
    """Build the pipeline from the configured weights (shipped ones when unset)."""
    from fastmesh.pipeline import Pipeline

    t0 = time.perf_counter()
    pipe = Pipeline.from_pretrained(settings.weights, device=settings.device, threads=settings.torch_threads)
    log.info("pipeline loaded from %s in %.2f s", settings.weights or "shipped weights", time.perf_counter() - t0)
    return pipe


class JobControl:
    """The pipeline's ``progress`` and ``should_cancel`` callbacks for one attempt of one job.

    Progress is written at most every ``progress_interval`` seconds (and at each new stage); the
    cancel check reads the job's status at the same pace, so a DELETE or a requeue by the reaper
    stops the decoder within a fraction of a second.  Past ``job_timeout`` it asks to stop too.
    """

    def __init__(self, store: Store, job_id: str, attempt: int):
        self.store, self.job_id, self.attempt = store, job_id, attempt
        s = store.settings
        self.interval = s.progress_interval
        self.delay = s.debug_step_delay
        self.deadline = time.monotonic() + s.job_timeout
        self.last_write = self.last_check = 0.0
        self.stage = None
        self.lost = False       # the job is no longer ours (cancelled, requeued, failed by the reaper)
        self.timed_out = False

    def progress(self, stage: str, fraction: float) -> None:
        if self.delay:
            time.sleep(self.delay)
        now = time.monotonic()
        if stage == self.stage and now - self.last_write < self.interval:
            return
        self.stage, self.last_write = stage, now
        try:
            if not self.store.progress(self.job_id, self.attempt, stage, min(max(float(fraction), 0.0), 1.0)):
                self.lost = True
        except redis.RedisError as e:  # a blip must not kill the job; the final write will tell
            log.warning("progress write failed: %s", e)

    def should_cancel(self) -> bool:
        now = time.monotonic()
        if now > self.deadline:
            self.timed_out = True
        elif not self.lost and now - self.last_check >= self.interval:
            self.last_check = now
            try:
                self.lost = not self.store.still_mine(self.job_id, self.attempt)
            except redis.RedisError as e:
                log.warning("cancel check failed: %s", e)
        return self.lost or self.timed_out or STATE.shutting_down


def run_job(job_id: str, attempt: int) -> None:
    """RQ entry point.  Never raises for a job's own failure: the outcome is written to the job."""
    STATE.ensure()
    store, name = STATE.store, STATE.name
    if not store.start(job_id, attempt, name):
        log.info("job %s attempt %d: not queued any more (cancelled or superseded), skipped", job_id, attempt)
        return
    STATE.running[job_id] = attempt
    try:
        with outcome_recorded(store, job_id, attempt):
            _run(store, job_id, attempt)
    finally:
        STATE.running.pop(job_id, None)
        STATE.jobs += 1
        give_back_memory()


def give_back_memory() -> None:
    """Between jobs: free what a job left in reference cycles and hand malloc's free pages back to the system, so
    a worker idles at the size of its model, not of its largest job."""
    gc.collect()
    trim_malloc()


@contextmanager
def outcome_recorded(store: Store, job_id: str, attempt: int) -> Iterator[None]:
    """Around a job's work: what its own failure handling (:func:`conclude`) leaves uncaught, recorded."""
    try:
        yield
    except JobTimeoutException:  # RQ's hard timeout, the backstop of our cooperative one
        store.finish(job_id, attempt, "failed", error=timeout_error(store.settings.job_timeout))
    except (redis.ConnectionError, redis.TimeoutError) as e:
        # Redis went away mid-job (restart, failover): not the job's fault, and reporting a failure
        # would fail too.  Wait for Redis, then hand the job back; only then return to RQ, whose own
        # bookkeeping after a job would otherwise meet the outage and stop the worker for good.
        log.warning("job %s: Redis unreachable (%s); handing it back when Redis returns", job_id, e)
        try:
            wait_for(lambda: _redis_answers(store), store.settings.redis_outage_wait, 0.5, what="Redis")
        except TimeoutError:
            raise e from None  # the worker exits; the API's reaper requeues the job once its heartbeat lapses
        _release(store, job_id, attempt, "Redis was unreachable")
    except Exception as e:  # a bug or Redis trouble: fail this job clearly rather than retry it forever
        if is_device_error(e):
            _device_failure(store, job_id, attempt, e, {})
            return
        log.exception("job %s crashed", job_id)
        store.finish(job_id, attempt, "failed",
                     error={"code": "internal", "message": f"worker error: {type(e).__name__}: {e}"[:500]})
    except BaseException:  # cold shutdown (SystemExit, KeyboardInterrupt): hand the job back, then go
        _release(store, job_id, attempt, "worker shutting down")
        raise


def _run(store: Store, job_id: str, attempt: int) -> None:
    job = prepare(store, job_id, attempt)
    if job is None:
        return
    if job.error is not None:
        conclude(store, job, job.error)
        return
    try:
        result = STATE.pipeline.generate(job.shape, job.params, progress=job.ctl.progress,
                                         should_cancel=job.ctl.should_cancel)
    except Exception as e:  # noqa: BLE001 - conclude records it, or raises what it does not know
        result = e
    conclude(store, job, result)


@dataclass
class Job:
    """One attempt of a job, read from Redis and ready for the pipeline (``error``: its input would not load)."""

    job_id: str
    attempt: int
    ctl: JobControl
    params: object  # GenerateParams
    formats: list[str]
    timings: dict[str, float]
    shape: object = None  # fastmesh.shapes.shape.Shape
    error: Exception | None = None
    device_errors: int = 0  # device errors it met on earlier attempts


def prepare(store: Store, job_id: str, attempt: int) -> Job | None:
    """The started job's parameters and shape; None when it failed already (its input is gone)."""
    from fastmesh.pipeline import GenerateParams

    job = store.get(job_id)
    timings = {"queue": job["started_at"] - job["created_at"]}
    blob = store.get_input(job_id)
    if blob is None:
        store.finish(job_id, attempt, "failed", timings=timings,
                     error={"code": "input_missing", "message": "the job's input is no longer stored"})
        return None
    names = {f.name for f in dataclasses.fields(GenerateParams)}
    out = Job(job_id, attempt, JobControl(store, job_id, attempt),
              GenerateParams(**{k: v for k, v in job["params"].items() if k in names}),
              job["params"].get("formats") or store.settings.default_formats, timings,
              device_errors=int(job.get("device_errors") or 0))
    try:
        # The API stores a cloud as uploaded: thinning it and estimating its normals are ours.
        out.shape = ready_cloud(shape_from_bytes(blob))
        # The upload's parse, and this attempt's from its start: reading the job and its input, parsing it.
        timings["load"] = float(job["timings"].get("load") or 0.0) + max(0.0, time.time() - job["started_at"])
    except Exception as e:  # noqa: BLE001 - conclude records it (a ShapeError: the input's fault)
        out.error = e
    return out


def conclude(store: Store, job: Job, outcome) -> None:
    """Record what the pipeline gave ``job``: its result (exported and stored), or the exception it raised
    (cancelled, refused, failed, a device error).  Raises what is no failure of the job (Redis away, a bug)."""
    from fastmesh.pipeline import Cancelled

    job_id, attempt, ctl, timings = job.job_id, job.attempt, job.ctl, job.timings
    try:
        if isinstance(outcome, BaseException):
            raise outcome
        result = outcome
        t0 = time.perf_counter()
        ctl.progress("export", 1.0)  # the pipeline reports overall fractions; it ended at 1
        files = {fmt: result.export(fmt) for fmt in job.formats}
        files["npz"] = result.mesh.to_npz() if result.mesh is not None else mesh_to_bytes(result.vertices,
                                                                                           result.faces)
    except Cancelled:
        if ctl.timed_out:
            store.finish(job_id, attempt, "failed", timings=timings, error=timeout_error(store.settings.job_timeout))
        elif STATE.shutting_down and not ctl.lost:
            _release(store, job_id, attempt, "worker shutting down")
        log.info("job %s attempt %d stopped (%s)", job_id, attempt,
                 "timeout" if ctl.timed_out else "cancelled or superseded" if ctl.lost else "shutdown")
        return
    except ShapeError as e:
        store.finish(job_id, attempt, "failed", timings=timings, error={"code": e.code, "message": e.message})
        return
    except ValueError as e:  # parameters the model refuses (e.g. more vertices than it was trained for)
        store.finish(job_id, attempt, "failed", timings=timings, error={"code": "invalid_parameter",
                                                                        "message": str(e)[:500]})
        return
    except (MemoryError, RuntimeError) as e:  # incl. GenerationError ("no_vertices", "no_faces")
        if is_device_error(e):
            _device_failure(store, job_id, attempt, e, timings)
            return
        if not hasattr(e, "code"):
            log.exception("job %s failed", job_id)
        store.finish(job_id, attempt, "failed", timings=timings, error={
            "code": getattr(e, "code", "generation_failed"),
            "message": getattr(e, "message", f"{type(e).__name__}: {e}")[:500]})
        return
    for fmt, data in files.items():
        store.put_result(job_id, fmt, data)
    timings["export"] = time.perf_counter() - t0  # the formats written and stored
    timings.update({k: float(v) for k, v in result.timings.items()})
    info = {"vertices": int(len(result.vertices)), "faces": int(len(result.faces)), "tokens": int(result.tokens),
            "formats": list(job.formats), "seed": result.info.get("chosen_seed"),
            "result_from": result.info.get("result_from"), "vertices_from": result.info.get("vertices_from"),
            "quality": result.quality,
            "placement": result.info.get("placement"), "notes": result.info.get("notes") or []}
    if not store.finish(job_id, attempt, "succeeded", result=info, timings=timings):
        # Cancelled (or taken over) during export: drop what we wrote unless another attempt owns it now.
        if (store.get(job_id) or {}).get("status") in (None, "cancelled", "failed"):
            store.redis.delete(*store.result_keys(job_id))
        return
    log.info("job %s succeeded: %d vertices, %d faces", job_id, info["vertices"], info["faces"])


def _redis_answers(store: Store) -> bool:
    try:
        return bool(store.redis.ping())
    except redis.RedisError:
        return False


def _release(store: Store, job_id: str, attempt: int, reason: str, **fields) -> bool:
    """Give a job back to the queue for a reason that is not the job's fault (``fields``: more to record in the
    job's hash).  False when the job was no longer this attempt's (cancelled, taken over)."""
    ok = store.requeue(job_id, attempt, **fields)
    if ok:
        log.warning("job %s handed back to the queue (%s)", job_id, reason)
    return ok


def _device_failure(store: Store, job_id: str, attempt: int, error: BaseException, timings: dict) -> None:
    """The accelerator failed during a job: this process is done (``STATE.device_failed``: it exits after this
    job and its supervisor starts a fresh one), and the job goes to another worker once, or fails.

    A fault of the device or of this process's CUDA context passes with the process; one the job itself
    triggers (its input driving a kernel out of bounds) comes back on the next worker, so a job gets one
    more attempt after its first device error and fails ``device_error`` after its second, or when its
    attempts (``max_attempts``) are spent.
    """
    STATE.device_failed = True
    what = f"{type(error).__name__}: {(str(error).strip().splitlines() or [''])[0]}"[:300]
    log.error("job %s attempt %d: device error (%s); this worker exits for a fresh CUDA context", job_id, attempt,
              what, exc_info=error)
    earlier = int((store.get(job_id) or {}).get("device_errors") or 0)
    if earlier == 0 and attempt < store.settings.max_attempts:
        if _release(store, job_id, attempt, "device error, for another worker", device_errors=1):
            store.count_job("retried")
        return
    again = ("; it had failed this way on another worker before, so it is likely to keep failing (report it with "
             "its input)" if earlier else "")
    store.finish(job_id, attempt, "failed", timings=timings, error={
        "code": "device_error",
        "message": f"the GPU failed while running this job ({what}); the worker that ran it restarts with a fresh "
                   f"GPU context{again}"[:500]})
