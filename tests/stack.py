"""The real service stack for the load, fault, bad-input and corpus tests.

Redis database ``FASTMESH_TEST_STACK_DB`` (default 12) of 127.0.0.1:6379, or a private
redis-server when none answers there; an API served in-process (:class:`service.processes.ServedApp`)
or as a restartable uvicorn subprocess (:class:`service.processes.ApiProcess`); ``fastmesh-worker``
subprocesses with the tiny random model.  Small, finite inputs made here.
"""

from __future__ import annotations

import contextlib
import io
import os
import uuid
from pathlib import Path

import httpx
import numpy as np
import redis

from fastmesh_jobs.runtime import wait_for
from fastmesh_jobs.settings import Settings
from service.processes import WorkerProcess, local_redis

DB = int(os.environ.get("FASTMESH_TEST_STACK_DB", "12"))
# Fast failure detection and no rate limits: the tests make hundreds of requests in seconds.
FAST = dict(heartbeat_interval=0.2, heartbeat_ttl=1.5, reaper_interval=0.2, progress_interval=0.05,
            rate_limit_per_minute=0, submit_rate_limit_per_minute=0)
FINAL = ("succeeded", "failed", "cancelled")
# In every key prefix, queue and worker name: runs of the suite at the same time (several people share
# one Redis) never see each other's jobs, and cleaning up deletes only this run's keys, never the database.
RUN = uuid.uuid4().hex[:8]


@contextlib.contextmanager
def flushed_redis(db: int):
    """URL of Redis database ``db``, emptied before and after: for modules that count every key in it."""
    url, server = local_redis(db)
    client = redis.Redis.from_url(url)
    client.flushdb()
    try:
        yield url
    finally:
        client.flushdb()
        if server:
            server.stop()


def make_settings(redis_url: str, name: str, **kw) -> Settings:
    return Settings(redis_url=redis_url, redis_prefix=f"s-{name}-{RUN}", queue_name=f"s-{name}-{RUN}",
                    **{**FAST, **kw})


def wp(settings: Settings, name: str, log_path, **env) -> WorkerProcess:
    """A ``fastmesh-worker`` subprocess named for this run (RQ refuses two live workers of one name)."""
    return WorkerProcess(settings, f"{name}-{RUN}", log_path, **env)


def sphere_points(n: int = 300, seed: int = 0, center=(3.0, -1.0, 2.0)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    p = rng.normal(size=(n, 3))
    return p / np.linalg.norm(p, axis=1, keepdims=True) + np.asarray(center)


def xyz_bytes(points: np.ndarray, fmt: str = "%.6f") -> bytes:
    buf = io.StringIO()
    np.savetxt(buf, points, fmt=fmt)
    return buf.getvalue().encode()


def write_inputs(directory: Path, n: int = 3) -> Path:
    """A few small valid shapes: point clouds (xyz, npy) and a mesh (obj)."""
    import trimesh

    directory.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        (directory / f"ball{i}.xyz").write_bytes(xyz_bytes(sphere_points(seed=i)))
    np.save(directory / "cloud.npy", sphere_points(seed=9))
    trimesh.creation.icosphere(1).export(directory / "ico.obj")
    return directory


def job(url: str, job_id: str, headers=None) -> dict:
    r = httpx.get(f"{url}/v1/jobs/{job_id}", headers=headers, timeout=30)
    assert r.status_code == 200, r.text
    return r.json()


def wait_final(url: str, job_id: str, timeout: float = 60.0) -> dict:
    return wait_for(lambda: (j := job(url, job_id))["status"] in FINAL and j, timeout, 0.05,
                    what=f"job {job_id} to finish")


def assert_error(r: httpx.Response, status: int | tuple[int, ...], code: str | None = None) -> dict:
    """An error answer of the documented shape; ``status`` may list the acceptable ones."""
    ok = status if isinstance(status, tuple) else (status,)
    assert r.status_code in ok, (r.status_code, r.text[:500])
    assert r.headers["content-type"].startswith("application/json"), r.headers
    body = r.json()
    assert set(body) == {"error"} and set(body["error"]) == {"code", "message"}, body
    assert body["error"]["message"], body
    if code:
        assert body["error"]["code"] == code, body
    return body["error"]


def forget_run(url: str) -> None:
    """Delete this run's keys (our prefixes, RQ's queue and registry keys named after our queues)."""
    client = redis.Redis.from_url(url)
    keys = list(client.scan_iter(f"*{RUN}*", count=1000))
    # RQ's own job hashes are named after our job ids ("<id>-<attempt>"), not after the queue.
    ids = {k.decode().rsplit(":job:", 1)[1] for k in keys if b":job:" in k}
    for pattern in ("rq:job:*", "rq:execution*"):
        keys += [k for k in client.scan_iter(pattern, count=1000)
                 if k.decode().split(":")[2].rsplit("-", 1)[0] in ids]
    for i in range(0, len(keys), 500):
        client.delete(*keys[i:i + 500])


def printed(proc, lines: list[str], text: str):
    """A ``wait_for`` condition: reads ``proc``'s stdout a line at a time (kept in ``lines``) until one holds
    ``text``; raises with everything printed if the process exits first."""
    def seen() -> bool:
        line = proc.stdout.readline()
        if not line and proc.poll() is not None:
            raise RuntimeError("service.run exited:\n" + "".join(lines))
        lines.append(line)
        return text in line
    return seen


def post(url: str, name: str, data: bytes, headers=None, timeout: float = 60, **fields) -> httpx.Response:
    """``POST /v1/jobs`` of ``data`` as the file ``name``, with ``fields`` as form fields (sent as strings)."""
    return httpx.post(f"{url}/v1/jobs", files={"file": (name, data)}, data={k: str(v) for k, v in fields.items()},
                      headers=headers, timeout=timeout)
