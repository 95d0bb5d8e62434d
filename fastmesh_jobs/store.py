"""Jobs, inputs and results in Redis; shared by the API and the workers.

Layout (``P`` is ``Settings.redis_prefix``)::

    P:job:<id>              hash: owner status attempt stage fraction created_at started_at finished_at
                                  params input result timings error filename worker webhook
                                  (JSON-encoded values)
    P:input:<id>            npz bytes of the parsed input shape
    P:result:<id>:<fmt>     exported mesh (glb/obj/ply) and ``npz`` (vertices, faces) for other formats
    P:hb:<id>               heartbeat of the attempt running the job (value = attempt), short TTL
    P:running               set of job ids in status "running" (what the reaper scans)
    P:queued                zset job id -> time enqueued (the reaper finds queue entries lost with a worker)
    P:suspects              hash job id -> when its queue entry was first seen missing
    P:owned:<owner>         zset job id -> created_at: an API key's jobs (``service.listing``)
    P:webhooks              zset job id -> when its webhook delivery is due (``service.webhooks``)
    P:idem:<owner>:<sha>    "<job id> <request fingerprint>" for Idempotency-Key (+ " pending" until created)
    P:rate:<kind>:<owner>:<minute>   fixed-window request counters
    P:authok:<address>:<owner>  a key that authenticated from an address before a lockout (``auth_admit``)
    P:workers               zset worker name -> last heartbeat (unix seconds)
    P:vertex_limit          max_vertices of the model the last heartbeating worker loaded
    P:worker:<name>         hash: pid host loads jobs weights started_at
    P:stats:jobs            hash: submitted succeeded failed cancelled retried
    P:stats:stage:<stage>   hash: count sum b:<le> (a histogram of stage durations)
    P:stats:distance:<cd|hd>  hash: count sum b:<le> (a histogram of result-to-input distances)

Every status change is a compare-and-set on (status, attempt) in one Lua script, so a late
write from a worker that was presumed dead, or that lost a race with a DELETE, changes nothing.
The RQ queue only carries ``(job id, attempt)``; this hash is the truth about a job.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import time
import uuid
from datetime import datetime, timezone

import numpy as np
import redis
from rq import Queue

from fastmesh.shapes.shape import EXPORT_FORMATS, Normalization, Shape
from fastmesh.shapes.texture import SurfaceTexture

from .settings import Settings

STATUSES = ("queued", "running", "succeeded", "failed", "cancelled")
FINAL = ("succeeded", "failed", "cancelled")
TIMING_KEYS = ("queue", "load", "encode", "vertices", "enhancer", "faces", "filtering", "export", "total")
STAGE_BUCKETS = (0.01, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 120.0, 300.0, 600.0)
# Result-to-input distance (% of the input's size): validation meshes sit at CD 2-5, HD 8-25.
DISTANCE_BUCKETS = (0.5, 1.0, 2.0, 3.0, 4.0, 5.0, 7.5, 10.0, 15.0, 20.0, 30.0, 50.0)
TASK = "worker.jobs.run_job"  # by name: the API never imports the worker (or torch)
RQ_GRACE = 30  # RQ's hard timeout backs up our cooperative one by this many seconds
PENDING_TTL = 10  # seconds an Idempotency-Key stays claimed by a request that has not created its job yet

# KEYS: failed authentications of an address this minute, the (address, owner) pair's mark.  ARGV: limit, ttl.
_AUTH_ADMIT = """
local limit = tonumber(ARGV[1])
if limit <= 0 then return 1 end
if tonumber(redis.call('GET', KEYS[1]) or '0') < limit then
  redis.call('SET', KEYS[2], '1', 'EX', ARGV[2])
  return 1
end
return redis.call('EXISTS', KEYS[2])
"""
AUTH_REMEMBER_SECONDS = 3600  # a key that authenticated from an address is not locked out there for this long

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

# KEYS: queued zset.  ARGV: job id, now, limit.  Admission to the queue: check and add in one step, so
# concurrent submissions cannot all see room and overshoot the limit together.
_ADMIT = """
if redis.call('ZCARD', KEYS[1]) >= tonumber(ARGV[3]) then return 0 end
redis.call('ZADD', KEYS[1], ARGV[2], ARGV[1])
return 1
"""

# KEYS: job, hb.  ARGV: attempt, hb ttl ms
_HEARTBEAT = """
if redis.call('HGET', KEYS[1], 'status') ~= 'running' then return 0 end
if redis.call('HGET', KEYS[1], 'attempt') ~= ARGV[1] then return 0 end
redis.call('SET', KEYS[2], ARGV[1], 'PX', ARGV[2])
return 1
"""


class QueueFull(Exception):
    """``create`` found ``max_queued`` jobs already waiting."""


def iso(t: float | None) -> str | None:
    """Unix seconds -> ISO 8601 UTC ('2025-01-01T12:00:00.123456Z'), None stays None."""
    if t is None:
        return None
    return datetime.fromtimestamp(t, timezone.utc).isoformat().replace("+00:00", "Z")


def _exact(values: np.ndarray) -> np.ndarray:
    """``values`` as float32 where that holds every value exactly (most mesh files store float32), else float64."""
    values = np.asarray(values, np.float64)
    small = values.astype(np.float32)
    return small if np.array_equal(small.astype(np.float64), values) else values


def shape_to_bytes(shape: Shape) -> bytes:
    """The parsed input, as it travels to the worker and sits in Redis for the job's retention (npz, no pickle).

    Lossless, so a job gives the result the CLI and the Python API give for the same file and parameters
    (a change of 1e-8 in a coordinate can change which vertices the decoder samples): positions and normals
    are float32 where the file's numbers are float32 (12 bytes a point), float64 otherwise; faces int32.
    """
    arrays = {"vertices": _exact(shape.vertices)}
    if shape.faces is not None:
        arrays["faces"] = np.asarray(shape.faces, np.int32 if len(shape.vertices) < 2**31 else np.int64)
    if shape.normals is not None:
        arrays["normals"] = _exact(shape.normals)
    if shape.texture is not None:
        arrays.update(shape.texture.to_arrays())
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def shape_from_bytes(data: bytes) -> Shape:
    """The shape :func:`shape_to_bytes` stored (float64 positions and normals, int64 faces); also reads the
    unit-cube layout (``unit``, ``center``, ``scale``) of inputs stored by earlier versions."""
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        if "unit" in z:
            vertices = Normalization(center=z["center"], scale=float(z["scale"])).invert(z["unit"])
        else:
            vertices = z["vertices"].astype(np.float64)
        return Shape(vertices=vertices, faces=z["faces"].astype(np.int64) if "faces" in z else None,
                     normals=z["normals"].astype(np.float64) if "normals" in z else None,
                     texture=SurfaceTexture.from_arrays(z))


def mesh_to_bytes(vertices: np.ndarray, faces: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, vertices=np.asarray(vertices, np.float64), faces=np.asarray(faces, np.int64))
    return buf.getvalue()


def mesh_from_bytes(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        return z["vertices"], z["faces"]


class Store:
    """Redis access for one settings object.  Thread-safe (redis-py pools connections)."""

    def __init__(self, settings: Settings, client: redis.Redis | None = None):
        self.settings = settings
        # Bytes in, bytes out: RQ needs raw bytes and our blobs are binary; hashes are decoded by hand.
        self.redis = client or redis.Redis.from_url(settings.redis_url, socket_connect_timeout=5, socket_keepalive=True)
        self.prefix = settings.redis_prefix
        self.queue = Queue(settings.queue_name, connection=self.redis)
        self._transition = self.redis.register_script(_TRANSITION)
        self._start = self.redis.register_script(_START)
        self._heartbeat = self.redis.register_script(_HEARTBEAT)
        self._admit = self.redis.register_script(_ADMIT)

    # ------------------------------------------------------------------ keys
    def k_job(self, job_id: str) -> str:
        return f"{self.prefix}:job:{job_id}"

    def k_input(self, job_id: str) -> str:
        return f"{self.prefix}:input:{job_id}"

    def k_result(self, job_id: str, fmt: str) -> str:
        return f"{self.prefix}:result:{job_id}:{fmt}"

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

    def k_preview(self, job_id: str) -> str:
        """Hash of the job's rendered previews (``service.preview``)."""
        return f"{self.prefix}:preview:{job_id}"

    def result_keys(self, job_id: str) -> list[str]:
        return [self.k_result(job_id, f) for f in (*EXPORT_FORMATS, "npz")]

    # ------------------------------------------------------------------ reading
    def get(self, job_id: str) -> dict | None:
        """The job's hash, values decoded (JSON fields parsed), or None if unknown / expired."""
        raw = self.redis.hgetall(self.k_job(job_id))
        if not raw:
            return None
        out = {}
        for k, v in raw.items():
            k, v = k.decode(), v.decode()
            out[k] = v if k in ("owner", "status", "worker", "rq_id") else json.loads(v)
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

    def workers_alive(self) -> list[str]:
        cutoff = time.time() - self.settings.heartbeat_ttl
        return [w.decode() for w in self.redis.zrangebyscore(f"{self.prefix}:workers", cutoff, "+inf")]

    def queue_position(self, job: dict) -> int | None:
        """0-based place in the queue of a queued job (None when not queued or unknown)."""
        if job["status"] != "queued" or not job.get("rq_id"):
            return None
        return self.redis.lpos(self.queue.key, job["rq_id"])  # RQ pushes right, pops left

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
            argv += [k, v if k in ("owner", "status", "worker", "rq_id") else json.dumps(v)]
        keys = [self.k_job(job_id), self.k_hb(job_id), self.k_running, self.k_queued, self.k_webhooks,
                *(expire or [])]
        return bool(self._transition(keys=keys, args=argv))

    def create(self, owner: str, params: dict, input_info: dict, shape_bytes: bytes, load_seconds: float,
               max_queued: int | None = None, job_id: str | None = None, webhook: dict | None = None) -> str:
        """Store a new queued job and its input, and enqueue it.  Returns the job id.

        ``job_id`` (from :meth:`new_id`) lets a caller name the job before it exists; ``webhook``
        (:func:`service.webhooks.new_webhook`) is delivered when the job finishes.
        Raises :class:`QueueFull` when ``max_queued`` jobs are already queued (checked atomically).
        """
        job_id = job_id or self.new_id()
        now = time.time()
        if max_queued is not None and not self._admit(keys=[self.k_queued], args=[job_id, now, max_queued]):
            raise QueueFull(job_id)
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
            pipe.hincrby(f"{self.prefix}:stats:jobs", "submitted", 1)
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
        return bool(self._start(keys=[self.k_job(job_id), self.k_hb(job_id), self.k_running, self.k_queued],
                                args=[str(attempt), json.dumps(time.time()), worker, hb_ms, job_id]))

    def heartbeat(self, job_id: str, attempt: int) -> bool:
        hb_ms = int(self.settings.heartbeat_ttl * 1000)
        return bool(self._heartbeat(keys=[self.k_job(job_id), self.k_hb(job_id)], args=[str(attempt), hb_ms]))

    def progress(self, job_id: str, attempt: int, stage: str, fraction: float) -> bool:
        """Record progress; False when the job is no longer this attempt's to run (cancelled, requeued)."""
        return self.transition(job_id, "running", {"stage": stage, "fraction": round(float(fraction), 4)},
                               attempt=attempt)

    def still_mine(self, job_id: str, attempt: int) -> bool:
        st, at = self.redis.hmget(self.k_job(job_id), "status", "attempt")
        return st == b"running" and at is not None and int(at) == attempt

    def finish(self, job_id: str, attempt: int | None, status: str, *, allowed=("running",),
               result: dict | None = None, error: dict | None = None, timings: dict | None = None) -> bool:
        """Move a job to a final status, set the retention clock on it, its input and results."""
        job = self.get(job_id)
        if job is None:
            return False
        now = time.time()
        t = dict(job.get("timings") or {})
        t.update(timings or {})
        t["total"] = now - job["created_at"]
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
                pipe.hincrby(f"{self.prefix}:stats:jobs", status, 1)
                # The key's list of jobs lives as long as its last job to finish.
                pipe.expire(self.k_owned(job["owner"]), self.settings.retention_seconds)
                if status == "succeeded":
                    for k, v in t.items():
                        if v is not None:
                            self._observe(pipe, f"stage:{k}", v, STAGE_BUCKETS)
                    quality = (result or {}).get("quality") or {}
                    for k in ("cd", "hd"):
                        if quality.get(k) is not None:
                            self._observe(pipe, f"distance:{k}", quality[k], DISTANCE_BUCKETS)
                pipe.execute()
        return ok

    def _observe(self, pipe, name: str, value: float, buckets: tuple[float, ...]) -> None:
        key = f"{self.prefix}:stats:{name}"
        pipe.hincrby(key, "count", 1)
        pipe.hincrbyfloat(key, "sum", float(value))
        for le in buckets:
            if value <= le:
                pipe.hincrby(key, f"b:{le}", 1)

    def stage_stats(self) -> dict[str, dict[str, float]]:
        """Per stage of succeeded jobs: count, sum and b:<le> of its duration in seconds."""
        return self._histograms("stage")

    def distance_stats(self) -> dict[str, dict[str, float]]:
        """Per distance (cd, hd) of succeeded jobs' results to their inputs: count, sum and b:<le>."""
        return self._histograms("distance")

    def _histograms(self, kind: str) -> dict[str, dict[str, float]]:
        out = {}
        for key in self.redis.scan_iter(f"{self.prefix}:stats:{kind}:*"):
            name = key.decode().rsplit(":", 1)[1]
            out[name] = {k.decode(): float(v) for k, v in self.redis.hgetall(key).items()}
        return out

    def job_counters(self) -> dict[str, int]:
        return {k.decode(): int(v) for k, v in self.redis.hgetall(f"{self.prefix}:stats:jobs").items()}

    # ------------------------------------------------------------------ user actions
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

    # ------------------------------------------------------------------ blobs
    def put_result(self, job_id: str, fmt: str, data: bytes, ttl: int | None = None) -> None:
        self.redis.set(self.k_result(job_id, fmt), data, ex=ttl or self.settings.retention_seconds)

    def get_result(self, job_id: str, fmt: str) -> bytes | None:
        return self.redis.get(self.k_result(job_id, fmt))

    def get_input(self, job_id: str) -> bytes | None:
        return self.redis.get(self.k_input(job_id))

    def ttl_of(self, job_id: str) -> int:
        t = self.redis.ttl(self.k_job(job_id))
        return t if t and t > 0 else self.settings.retention_seconds

    # ------------------------------------------------------------------ idempotency and rate limits
    def _k_idem(self, owner: str, key: str) -> str:
        return f"{self.prefix}:idem:{owner}:{hashlib.sha256(key.encode()).hexdigest()}"

    def idempotency_get(self, owner: str, key: str) -> str | None:
        """What ``key`` names: "<job id> <fingerprint>" or, while being created, "<job id> <fingerprint> pending"."""
        raw = self.redis.get(self._k_idem(owner, key))
        return raw.decode() if raw is not None else None

    def idempotency_claim(self, owner: str, key: str, job_id_fp: str) -> str | None:
        """Claim ``key`` for ``job_id_fp`` ("<job id> <fingerprint> pending").  Returns the existing claim, or
        None if ours.

        The claim lives ``PENDING_TTL`` seconds until :meth:`idempotency_replace` names the job: an API
        killed in between must not block the key for the whole retention time.
        """
        k = self._k_idem(owner, key)
        if self.redis.set(k, job_id_fp, nx=True, ex=PENDING_TTL):
            return None
        old = self.redis.get(k)
        return old.decode() if old else None

    def idempotency_replace(self, owner: str, key: str, old: str, new: str) -> bool:
        """Swap claim ``old`` for ``new`` (compare-and-set)."""
        k = self._k_idem(owner, key)
        with self.redis.pipeline() as pipe:
            try:
                pipe.watch(k)
                cur = pipe.get(k)
                if cur is not None and cur.decode() != old:
                    return False
                pipe.multi()
                pipe.set(k, new, ex=self.settings.retention_seconds)
                pipe.execute()
                return True
            except redis.WatchError:
                return False

    def idempotency_release(self, owner: str, key: str) -> None:
        self.redis.delete(self._k_idem(owner, key))

    def rate_hit(self, kind: str, owner: str, limit: int) -> int:
        """Count one request in this minute's window; return seconds to wait (0 = allowed)."""
        if limit <= 0:
            return 0
        now = time.time()
        window = int(now // 60)
        k = f"{self.prefix}:rate:{kind}:{owner}:{window}"
        with self.redis.pipeline() as pipe:
            pipe.incr(k)
            pipe.expire(k, 61)
            count = pipe.execute()[0]
        return 0 if count <= limit else max(1, int(math.ceil((window + 1) * 60 - now)))

    def auth_admit(self, address: str, owner: str, limit: int, remember: int = AUTH_REMEMBER_SECONDS) -> bool:
        """Whether ``owner``'s key may pass from ``address``: while the address's failed authentications are
        under ``limit`` it may (and the pair is remembered for ``remember`` seconds); past it only a
        remembered pair may."""
        window = int(time.time() // 60)
        return bool(self.redis.eval(_AUTH_ADMIT, 2, f"{self.prefix}:rate:authfail:{address}:{window}",
                                    f"{self.prefix}:authok:{address}:{owner}", limit, remember))

    def rate_wait(self, kind: str, owner: str, limit: int) -> int:
        """Seconds to wait when this minute's window already holds ``limit`` hits (0 = allowed); counts nothing."""
        if limit <= 0:
            return 0
        now = time.time()
        window = int(now // 60)
        count = int(self.redis.get(f"{self.prefix}:rate:{kind}:{owner}:{window}") or 0)
        return 0 if count < limit else max(1, int(math.ceil((window + 1) * 60 - now)))

    # ------------------------------------------------------------------ workers
    def worker_beat(self, name: str, info: dict | None = None) -> None:
        ttl = int(math.ceil(max(self.settings.heartbeat_ttl * 3, 60)))
        with self.redis.pipeline() as pipe:
            pipe.zadd(f"{self.prefix}:workers", {name: time.time()})
            if info:
                pipe.hset(f"{self.prefix}:worker:{name}", mapping={k: json.dumps(v) for k, v in info.items()})
            pipe.expire(f"{self.prefix}:worker:{name}", ttl)
            if info and isinstance(info.get("max_vertices"), int):  # outlives the worker: see vertex_limit
                pipe.set(f"{self.prefix}:vertex_limit", info["max_vertices"], ex=self.settings.retention_seconds)
            # Forget workers silent for long (their own hash has expired by then too).
            pipe.zremrangebyscore(f"{self.prefix}:workers", "-inf", time.time() - ttl)
            pipe.execute()

    def vertex_limit(self) -> int | None:
        """The smallest ``max_vertices`` the live workers' models accept; with none alive, the limit the
        last worker reported (a job queued meanwhile waits for that model); None if no worker ever said."""
        names = self.workers_alive()
        if not names:
            last = self.redis.get(f"{self.prefix}:vertex_limit")
            return int(last) if last is not None else None
        with self.redis.pipeline() as pipe:
            for n in names:
                pipe.hget(f"{self.prefix}:worker:{n}", "max_vertices")
            limits = [json.loads(v) for v in pipe.execute() if v is not None]
        limits = [v for v in limits if isinstance(v, int)]
        return min(limits) if limits else None

    def worker_last_beat(self, name: str) -> float | None:
        """Unix time of the last heartbeat of the worker ``name`` (None: none on record)."""
        return self.redis.zscore(f"{self.prefix}:workers", name)

    def worker_gone(self, name: str) -> None:
        self.redis.zrem(f"{self.prefix}:workers", name)

    def worker_info(self, name: str) -> dict:
        return {k.decode(): json.loads(v) for k, v in self.redis.hgetall(f"{self.prefix}:worker:{name}").items()}


def timeout_error(seconds: float) -> dict:
    return {"code": "timeout", "message": f"the job ran longer than the {seconds:g} s limit (job_timeout)"}
