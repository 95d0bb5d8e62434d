"""A worker's resident memory before, at the peak of and after a job on a 500,000-point cloud.

    python benchmarks/worker_memory.py [--points 500000] [--weights DIR] [--jobs 2]

Starts its own redis-server, the API (uvicorn subprocess) and one ``fastmesh-worker`` (shipped weights unless
``--weights``), submits ``--jobs`` jobs one after another of a ``--points``-point ``.npy`` of an ellipsoid's
surface (no normals: the worker estimates them) with ``--candidates`` (1), samples the worker's RSS every 20 ms and
prints one JSON line per job: its status, seconds, the worker's RSS before, at its peak and 2 s after the job.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from attack_memory import Peak, npy, rss_mib  # noqa: E402

from fastmesh_jobs.runtime import wait_for  # noqa: E402
from fastmesh_jobs.settings import Settings  # noqa: E402
from service.processes import ApiProcess, RedisServer, WorkerProcess, free_port  # noqa: E402

SETTLE_SECONDS = 2.0  # after a job, before its "after" is read


def ellipsoid(n: int) -> bytes:
    p = np.random.default_rng(0).normal(size=(n, 3))
    return npy(p / np.linalg.norm(p, axis=1, keepdims=True) * [1.0, 0.7, 0.4])


def one_job(url: str, data: bytes, worker: WorkerProcess, candidates: int) -> dict:
    with Peak(worker.pid) as peak:
        t0 = time.perf_counter()
        r = httpx.post(f"{url}/v1/jobs", files={"file": ("big.npy", data)}, data={"candidates": str(candidates)},
                       timeout=600)
        r.raise_for_status()
        job_id = r.json()["id"]
        final = wait_for(lambda: (j := httpx.get(f"{url}/v1/jobs/{job_id}").json())["status"]
                         in ("succeeded", "failed", "cancelled") and j, 1800, 0.2, what="the job")
        took = time.perf_counter() - t0
        time.sleep(SETTLE_SECONDS)
    return {"status": final["status"], "error": final.get("error"), "seconds": round(took, 1),
            "worker_before_mib": round(peak.before), "worker_peak_mib": round(peak.peak),
            "worker_after_mib": round(rss_mib(worker.pid))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, default=500_000)
    ap.add_argument("--jobs", type=int, default=2, help="jobs run one after another")
    ap.add_argument("--candidates", type=int, default=1, help="candidates of each job")
    ap.add_argument("--weights", default=None, help="weights folder of the worker (default: shipped)")
    args = ap.parse_args()
    redis_server = RedisServer(directory=tempfile.mkdtemp(prefix="fastmesh-workermem-"))
    settings = Settings(redis_url=redis_server.url, weights=args.weights, rate_limit_per_minute=0,
                        submit_rate_limit_per_minute=0, port=free_port(), max_points=max(args.points, 500_000))
    url = f"http://127.0.0.1:{settings.port}"
    api = ApiProcess(settings, port=settings.port)
    worker = None
    try:
        api.wait_ready()
        worker = WorkerProcess(settings, f"workermem-{os.getpid()}").wait_ready(300)
        data = ellipsoid(args.points)
        for i in range(args.jobs):
            row = one_job(url, data, worker, args.candidates)
            print(json.dumps({"job": i + 1, "points": args.points, "candidates": args.candidates, **row}), flush=True)
    finally:
        api.stop()
        if worker is not None:
            worker.stop()
        redis_server.stop()


if __name__ == "__main__":
    main()
