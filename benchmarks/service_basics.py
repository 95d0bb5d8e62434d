"""Basic figures of the service on this machine: worker start-up, job latency, polling latency, death detection.

    python benchmarks/service_basics.py [--jobs 20] [--polls 500] [--weights DIR]

Uses the Redis on 127.0.0.1:6379 (database 11, flushed) or starts one, an API served in this process,
and real ``fastmesh-worker`` processes.  Without ``--weights`` the tiny random model is used, so the
job figures measure the service's own overhead, not the model.  Prints one JSON object.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import signal
import statistics
import tempfile
import time

import httpx
import numpy as np
import redis

from fastmesh_jobs.runtime import wait_for
from fastmesh_jobs.settings import Settings
from service.processes import ServedApp, WorkerProcess, local_redis


def pct(xs: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(xs), q))


def sphere(n: int = 2000) -> bytes:
    p = np.random.default_rng(0).normal(size=(n, 3))
    buf = io.StringIO()
    np.savetxt(buf, p / np.linalg.norm(p, axis=1, keepdims=True), fmt="%.5f")
    return buf.getvalue().encode()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--jobs", type=int, default=20)
    ap.add_argument("--polls", type=int, default=500)
    ap.add_argument("--weights", default=None)
    ap.add_argument("--max-vertices", type=int, default=12)
    args = ap.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    weights = args.weights
    if weights is None:
        from fastmesh.pipeline import Pipeline

        weights = tempfile.mkdtemp(prefix="fastmesh-bench-weights-")
        Pipeline.random("tiny", seed=0).save(weights)
    url, server = local_redis(11)
    client = redis.Redis.from_url(url)
    client.flushdb()
    s = Settings(redis_url=url, redis_prefix="bench", queue_name="bench", weights=weights,
                 rate_limit_per_minute=0, submit_rate_limit_per_minute=0)
    app = ServedApp(s)
    out: dict = {"weights": args.weights or "random tiny", "settings": {
        "heartbeat_interval": s.heartbeat_interval, "heartbeat_ttl": s.heartbeat_ttl,
        "reaper_interval": s.reaper_interval}}
    workers = []
    try:
        t = time.perf_counter()
        w = WorkerProcess(s, "bench-w1").wait_ready(120)
        workers.append(w)
        out["worker_startup_s"] = round(time.perf_counter() - t, 2)

        data = sphere()
        http = httpx.Client(base_url=app.url, timeout=60)
        e2e, queue, total = [], [], []
        for i in range(args.jobs):
            t = time.perf_counter()
            job = http.post("/v1/jobs", files={"file": ("s.xyz", data)},
                            data={"seed": str(i), "max_vertices": str(args.max_vertices)}).json()
            r = http.get(f"/v1/jobs/{job['id']}/result", params={"wait": 60})
            assert r.status_code == 200, r.text
            e2e.append(time.perf_counter() - t)
            j = http.get(f"/v1/jobs/{job['id']}").json()
            queue.append(j["timings"]["queue"])
            total.append(j["timings"]["total"])
        out["job_end_to_end_s"] = {"p50": round(pct(e2e, 50), 3), "p95": round(pct(e2e, 95), 3)}
        out["job_queue_wait_s_p50"] = round(pct(queue, 50), 4)
        out["job_total_s_p50"] = round(pct(total, 50), 3)

        lat = []
        for _ in range(args.polls):
            t = time.perf_counter()
            http.get(f"/v1/jobs/{job['id']}")
            lat.append((time.perf_counter() - t) * 1000)
        out["poll_ms_idle"] = {"p50": round(pct(lat, 50), 2), "p99": round(pct(lat, 99), 2),
                               "mean": round(statistics.fmean(lat), 2)}

        # SIGKILL a worker in the middle of a (slowed-down) job; time until the job is queued again.
        slow = WorkerProcess(s, "bench-slow", FASTMESH_DEBUG_STEP_DELAY="2").wait_ready(120)
        workers.append(slow)
        w.stop()
        job = http.post("/v1/jobs", files={"file": ("s.xyz", data)}, data={"max_vertices": "20"}).json()
        wait_for(lambda: http.get(f"/v1/jobs/{job['id']}").json()["status"] == "running", 60)
        os.kill(slow.pid, signal.SIGKILL)
        t = time.perf_counter()
        wait_for(lambda: http.get(f"/v1/jobs/{job['id']}").json()["status"] == "queued", 120, 0.05)
        out["sigkill_to_requeue_s"] = round(time.perf_counter() - t, 2)
    finally:
        for w in workers:
            w.stop()
        app.stop()
        client.flushdb()
        if server:
            server.stop()
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
