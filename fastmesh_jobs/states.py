"""A job's hash and its states: submit, start, progress, finish, cancel, requeue, delete, and how the API shows it.

Keys (``P`` is ``Settings.redis_prefix``)::

    P:job:<id>              hash: owner status attempt stage fraction created_at started_at finished_at
                                  params input result timings error filename worker webhook
                                  (JSON-encoded values)
    P:hb:<id>               heartbeat of the attempt running the job (value = attempt), short TTL
    P:running               set of job ids in status "running" (what the reaper scans)
    P:queued                zset job id -> time enqueued (the reaper finds queue entries lost with a worker)
    P:owned:<owner>         zset job id -> created_at: an API key's jobs (``service.listing``)
    P:webhooks              zset job id -> when its webhook delivery is due (``service.webhooks``)

Every status change is a compare-and-set on (status, attempt) in one Lua script, so a late
write from a worker that was presumed dead, or that lost a race with a DELETE, changes nothing.
The RQ queue only carries ``(job id, attempt)``; this hash is the truth about a job.
"""

from __future__ import annotations

import json
import math
import time
import uuid
from datetime import datetime, timezone

from .blobs import Blobs
from .limits import Limits
from .telemetry import Telemetry

STATUSES = ("queued", "running", "succeeded", "failed", "cancelled")
FINAL = ("succeeded", "failed", "cancelled")
# ``total``: the job's seconds outside the queue, each in one of the stages before it (``queue`` apart).
TIMING_KEYS = ("queue", "load", "encode", "vertices", "enhancer", "faces", "filtering", "weighing", "export", "total")
TASK = "worker.jobs.run_job"  # by name: the API never imports the worker (or torch)
RQ_GRACE = 30  # RQ's hard timeout backs up our cooperative one by this many seconds
_PLAIN = ("owner", "status", "worker", "rq_id")  # fields stored as strings; every other one is JSON

# KEYS: job, hb, running set, queued zset, webhooks zset, keys to EXPIRE...
# ARGV: allowed statuses (comma list), attempt ('' = any), ttl ('' = keep), job id,
#       final ('1' = leaves running/queued, '2' = that and, for a job with a webhook, its delivery is due),
#       field, value, ...
# The delivery is queued in the same step as the final status: no process dying in between can lose it.
_TRANSITION = """
local st = redis.call('HGET', KEYS[1], 'status')
if not st then return 0 end
local ok = false
for s in string.gmatch(ARGV[1], '[^,]+') do if s == st then ok = true end end
if not ok then return 0 end
if ARGV[2] ~= '' and redis.call('HGET', KEYS[1], 'attempt') ~= ARGV[2] then return 0 end
if #ARGV > 5 then redis.call('HSET', KEYS[1], unpack(ARGV, 6)) end
if ARGV[5] ~= '0' then
  redis.call('SREM', KEYS[3], ARGV[4]); redis.call('ZREM', KEYS[4], ARGV[4]); redis.call('DEL', KEYS[2])
end
if ARGV[5] == '2' and redis.call('HEXISTS', KEYS[1], 'webhook') == 1 then
  redis.call('ZADD', KEYS[5], 'NX', 0, ARGV[4])
end
if ARGV[3] ~= '' then
  for i = 1, #KEYS do if i == 1 or i > 5 then redis.call('EXPIRE', KEYS[i], ARGV[3]) end end
end
return 1
"""

# KEYS: job, hb, running set, queued zset.  ARGV: attempt, now, worker, hb ttl ms, job id
_START = """
if redis.call('HGET', KEYS[1], 'status') ~= 'queued' then return 0 end
if redis.call('HGET', KEYS[1], 'attempt') ~= ARGV[1] then return 0 end
redis.call('HSET', KEYS[1], 'status', 'running', 'started_at', ARGV[2], 'worker', ARGV[3],
           'stage', '"starting"', 'fraction', '0')
redis.call('SET', KEYS[2], ARGV[1], 'PX', ARGV[4])
redis.call('SADD', KEYS[3], ARGV[5])
redis.call('ZREM', KEYS[4], ARGV[5])
return 1
"""

# KEYS: job, hb.  ARGV: attempt, hb ttl ms
_HEARTBEAT = """
if redis.call('HGET', KEYS[1], 'status') ~= 'running' then return 0 end
if redis.call('HGET', KEYS[1], 'attempt') ~= ARGV[1] then return 0 end
redis.call('SET', KEYS[2], ARGV[1], 'PX', ARGV[2])
return 1
"""


def iso(t: float | None) -> str | None:
    """Unix seconds -> ISO 8601 UTC ('2025-01-01T12:00:00.123456Z'), None stays None."""
    if t is None:
        return None
    return datetime.fromtimestamp(t, timezone.utc).isoformat().replace("+00:00", "Z")


def timeout_error(seconds: float) -> dict:
    return {"code": "timeout", "message": f"the job ran longer than the {seconds:g} s limit (job_timeout)"}


class JobStates(Blobs, Telemetry, Limits):
    """The job hash and its compare-and-set transitions, over the job's blobs (they expire with it), the
    counters (each change counted in its own step) and the queue's size limit (checked on submission)."""

    # ------------------------------------------------------------------ keys
    def k_job(self, job_id: str) -> str:
        return f"{self.prefix}:job:{job_id}"

    def k_hb(self, job_id: str) -> str:
        return f"{self.prefix}:hb:{job_id}"

    @property
    def k_running(self) -> str:
        return f"{self.prefix}:running"

    @property
    def k_queued(self) -> str:
        return f"{self.prefix}:queued"

    @property
    def k_webhooks(self) -> str:
        return f"{self.prefix}:webhooks"

    def k_owned(self, owner: str) -> str:
        return f"{self.prefix}:owned:{owner}"

    # ------------------------------------------------------------------ reading
    def get(self, job_id: str) -> dict | None:
        """The job's hash, values decoded (JSON fields parsed), or None if unknown / expired."""
        raw = self.redis.hgetall(self.k_job(job_id))
        if not raw:
            return None
        out = {}
        for k, v in raw.items():
            k, v = k.decode(), v.decode()
            out[k] = v if k in _PLAIN else json.loads(v)
        out["id"] = job_id
        return out

    def public(self, job: dict) -> dict:
        """The job as ``GET /v1/jobs/{id}`` shows it (``service.schemas.Job``)."""
        timings = {k: None for k in TIMING_KEYS}
        timings.update({k: v for k, v in (job.get("timings") or {}).items() if k in TIMING_KEYS})
        return {
            "id": job["id"],
            "status": job["status"],
            "progress": {"stage": job.get("stage"), "fraction": job.get("fraction", 0.0)},
            "created_at": iso(job.get("created_at")),
            "started_at": iso(job.get("started_at")),
            "finished_at": iso(job.get("finished_at")),
            "params": job.get("params"),
            "input": job.get("input"),
            "result": job.get("result"),
            "timings": timings,
            "error": job.get("error"),
            # The retention clock runs from creation and starts again when the job finishes (``finish``).
            "expires_at": iso((job.get("finished_at") or job["created_at"]) + self.settings.retention_seconds),
            "webhook": job.get("webhook"),
        }

    def queue_depth(self) -> int:
        return self.queue.count

    def running_count(self) -> int:
        return int(self.redis.scard(self.k_running))

    def queue_position(self, job: dict) -> int | None:
        """0-based place in the queue of a queued job (None when not queued or unknown)."""
        if job["status"] != "queued" or not job.get("rq_id"):
            return None
        return self.redis.lpos(self.queue.key, job["rq_id"])  # RQ pushes right, pops left

    def still_mine(self, job_id: str, attempt: int) -> bool:
        st, at = self.redis.hmget(self.k_job(job_id), "status", "attempt")
        return st == b"running" and at is not None and int(at) == attempt

    def ttl_of(self, job_id: str) -> int:
        t = self.redis.ttl(self.k_job(job_id))
        return t if t and t > 0 else self.settings.retention_seconds

    # ------------------------------------------------------------------ transitions
    def transition(self, job_id: str, allowed: str | tuple[str, ...], fields: dict | None = None,
                   attempt: int | None = None, final: bool = False, ttl: int | None = None,
                   expire: list[str] | None = None, notify: bool = False) -> bool:
        """Compare-and-set: apply ``fields`` only if status is in ``allowed`` (and attempt matches).

        ``notify`` (with ``final``): the job's webhook, if it has one, is queued for delivery in the same step.
        """
        allowed = allowed if isinstance(allowed, str) else ",".join(allowed)
        argv = [allowed, "" if attempt is None else str(attempt), "" if ttl is None else str(ttl), job_id,
                ("2" if notify else "1") if final else "0"]
        for k, v in (fields or {}).items():
            argv += [k, v if k in _PLAIN else json.dumps(v)]
        keys = [self.k_job(job_id), self.k_hb(job_id), self.k_running, self.k_queued, self.k_webhooks,
                *(expire or [])]
        return bool(self._script(_TRANSITION)(keys=keys, args=argv))

    def create(self, owner: str, params: dict, input_info: dict, shape_bytes: bytes, load_seconds: float,
               max_queued: int | None = None, job_id: str | None = None, webhook: dict | None = None) -> str:
        """Store a new queued job and its input, and enqueue it.  Returns the job id.

        ``job_id`` (from :meth:`new_id`) lets a caller name the job before it exists; ``webhook``
        (:func:`service.webhooks.new_webhook`) is delivered when the job finishes.
        Raises :class:`fastmesh_jobs.limits.QueueFull` when ``max_queued`` jobs are already queued (checked
        atomically).
        """
        job_id = job_id or self.new_id()
        now = time.time()
        if max_queued is not None:
            self.admit(self.k_queued, job_id, now, max_queued)
        ttl = self.settings.retention_seconds
        fields = {"owner": owner, "status": "queued", "attempt": 1, "stage": "queued", "fraction": 0.0,
                  "created_at": now, "started_at": None, "finished_at": None, "params": params,
                  "input": input_info, "result": None, "timings": {"load": load_seconds}, "error": None}
        if webhook is not None:
            fields["webhook"] = webhook
        with self.redis.pipeline() as pipe:
            pipe.set(self.k_input(job_id), shape_bytes, ex=ttl)
            pipe.hset(self.k_job(job_id), mapping={
                k: v if k in ("owner", "status") else json.dumps(v) for k, v in fields.items()})
            pipe.expire(self.k_job(job_id), ttl)
            pipe.zadd(self.k_owned(owner), {job_id: now})
            pipe.expire(self.k_owned(owner), ttl)
            self.count_job("submitted", pipe)
            pipe.execute()
        self.enqueue(job_id, 1)
        return job_id

    @staticmethod
    def new_id() -> str:
        return uuid.uuid4().hex

    def enqueue(self, job_id: str, attempt: int) -> None:
        rq_id = f"{job_id}-{attempt}"
        with self.redis.pipeline() as pipe:
            pipe.hset(self.k_job(job_id), "rq_id", rq_id)
            pipe.zadd(self.k_queued, {job_id: time.time()})
            pipe.execute()
        self.queue.enqueue_call(TASK, args=(job_id, attempt), job_id=rq_id,
                                timeout=int(math.ceil(self.settings.job_timeout)) + RQ_GRACE,
                                result_ttl=0, failure_ttl=self.settings.retention_seconds,
                                description=f"fastmesh job {job_id} attempt {attempt}")

    def start(self, job_id: str, attempt: int, worker: str) -> bool:
        """queued -> running for this attempt (and its first heartbeat), atomically."""
        hb_ms = int(self.settings.heartbeat_ttl * 1000)
        return bool(self._script(_START)(keys=[self.k_job(job_id), self.k_hb(job_id), self.k_running, self.k_queued],
                                         args=[str(attempt), json.dumps(time.time()), worker, hb_ms, job_id]))

    def heartbeat(self, job_id: str, attempt: int) -> bool:
        """Renew the heartbeat of a running attempt; False when the job is no longer this attempt's."""
        hb_ms = int(self.settings.heartbeat_ttl * 1000)
        return bool(self._script(_HEARTBEAT)(keys=[self.k_job(job_id), self.k_hb(job_id)],
                                             args=[str(attempt), hb_ms]))

    def progress(self, job_id: str, attempt: int, stage: str, fraction: float) -> bool:
        """Record progress; False when the job is no longer this attempt's to run (cancelled, requeued)."""
        return self.transition(job_id, "running", {"stage": stage, "fraction": round(float(fraction), 4)},
                               attempt=attempt)

    def requeue(self, job_id: str, attempt: int, **fields) -> bool:
        """running -> queued as attempt ``attempt`` + 1, enqueued again (``fields``: more to record in the job's
        hash).  False when the job was no longer this attempt's (cancelled, taken over)."""
        ok = self.transition(job_id, "running", {"status": "queued", "attempt": attempt + 1, "stage": "queued",
                                                 "fraction": 0.0, "worker": "", **fields}, attempt=attempt, final=True)
        if ok:
            self.enqueue(job_id, attempt + 1)
        return ok

    def finish(self, job_id: str, attempt: int | None, status: str, *, allowed=("running",),
               result: dict | None = None, error: dict | None = None, timings: dict | None = None) -> bool:
        """Move a job to a final status, set the retention clock on it, its input and results."""
        job = self.get(job_id)
        if job is None:
            return False
        now = time.time()
        t = dict(job.get("timings") or {})
        parsed = float(t.get("load") or 0.0)  # the upload's parse, before the job was created
        t.update(timings or {})
        # The queue apart: its parse, then from the start of its last attempt (what the worker counts in stages).
        started = job.get("started_at")
        t["queue"] = t.get("queue", (started or now) - job["created_at"])
        t["total"] = parsed + (now - started if started else 0.0)
        fields = {"status": status, "finished_at": now, "timings": t, "error": error,
                  "stage": "done" if status == "succeeded" else status,
                  "fraction": 1.0 if status == "succeeded" else job.get("fraction", 0.0)}
        if result is not None:
            fields["result"] = result
        ok = self.transition(job_id, allowed, fields, attempt=attempt, final=True, notify=True,
                             ttl=self.settings.retention_seconds,
                             expire=[self.k_input(job_id), *self.result_keys(job_id)])
        if ok:
            with self.redis.pipeline() as pipe:
                self.count_job(status, pipe)
                # The key's list of jobs lives as long as its last job to finish.
                pipe.expire(self.k_owned(job["owner"]), self.settings.retention_seconds)
                if status == "succeeded":
                    self.observe_success(pipe, t, result)
                pipe.execute()
        return ok

    def cancel(self, job_id: str) -> bool:
        """queued or running -> cancelled.  A running worker notices at its next cancel check."""
        job = self.get(job_id)
        if job is None or job["status"] not in ("queued", "running"):
            return False
        ok = self.finish(job_id, None, "cancelled", allowed=("queued", "running"),
                         error={"code": "cancelled", "message": "cancelled by request"})
        if ok and job.get("rq_id"):
            self.queue.remove(job["rq_id"])  # the worker would skip it anyway; this keeps the depth honest
        return ok

    def delete(self, job_id: str) -> None:
        self.redis.delete(self.k_job(job_id), self.k_input(job_id), self.k_hb(job_id), self.k_preview(job_id),
                          *self.result_keys(job_id))
        self.redis.srem(self.k_running, job_id)
        self.redis.zrem(self.k_queued, job_id)
