"""Throughput per worker count (and jobs batched per worker), and polling latency while the workers are saturated.

    python benchmarks/throughput.py                      # shipped weights, 1 then 2 workers, 60 s each
    python benchmarks/throughput.py --workers 1,1x4,2    # 1 worker, 1 worker running 4 jobs at once, 2 workers
    python benchmarks/throughput.py --tiny --duration 20 # the tiny random model: the service's own overhead

Starts everything it measures and stops it at the end: a private ``redis-server`` on a free port, the
API (:class:`service.processes.ApiProcess`: a uvicorn process of its own, as in production, sharing no GIL
with the load) and ``fastmesh-worker`` processes.  For each worker count it runs ``fastmesh loadtest``
(:mod:`fastmesh.remote.loadtest`) for ``--duration`` seconds with more simulated users than workers, so the queue
never drains, while a separate poller process times ``GET /v1/jobs/{id}`` every ``--poll-interval`` seconds.
Prints a table (``--json``: every report).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

from fastmesh.remote.loadtest import LoadConfig, percentiles, run
from fastmesh_jobs.settings import Settings
from service.processes import ApiProcess, RedisServer, WorkerProcess


def make_inputs(directory: Path, n_files: int = 4, n_points: int = 4000) -> Path:
    """Point clouds of stretched, rounded boxes (x y z per line), different per file."""
    for i in range(n_files):
        rng = np.random.default_rng(i)
        p = rng.normal(size=(n_points, 3))
        p /= np.abs(p).max(1, keepdims=True)
        p = np.sign(p) * np.abs(p) ** (0.5 + 0.1 * i) * [1.0, 0.5 + 0.1 * i, 0.4]
        np.savetxt(directory / f"box{i}.xyz", p, fmt="%.5f")
    return directory


def poller(url: str, seconds: float, interval: float, sample: str, params: dict) -> dict:
    """Upload ``sample`` once (it queues behind the load), then time GET /v1/jobs/{id} of that job for
    ``seconds``.  Milliseconds, and the answers seen (status code and job status)."""
    with httpx.Client(base_url=url, timeout=30) as http:
        job = http.post("/v1/jobs", files={"file": (Path(sample).name, Path(sample).read_bytes())},
                        data=params).json()
        lat, statuses = [], {}
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            t = time.perf_counter()
            r = http.get(f"/v1/jobs/{job['id']}")
            lat.append((time.perf_counter() - t) * 1000.0)
            key = f"{r.status_code} {r.json().get('status') if r.status_code == 200 else ''}".strip()
            statuses[key] = statuses.get(key, 0) + 1
            time.sleep(interval)
    return {"ms": percentiles(lat), "answers": statuses}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tiny", action="store_true", help="the tiny random model instead of the shipped weights")
    ap.add_argument("--weights", default=None, help="weights folder (default: the shipped weights)")
    ap.add_argument("--workers", default="1,2", help="worker counts to measure, in order (default 1,2); NxB: N "
                                                     "workers each running B jobs at once (FASTMESH_MAX_BATCH)")
    ap.add_argument("--duration", type=float, default=60.0, help="seconds of load per worker count (default 60)")
    ap.add_argument("--grace", type=float, default=120.0, help="seconds accepted jobs may take after that")
    ap.add_argument("--concurrency", type=int, default=None, help="simulated users (default 2 x workers + 2)")
    ap.add_argument("--inputs", default=None, help="folder of shapes (default: generated point clouds)")
    ap.add_argument("--max-vertices", type=int, default=None, help="per job (default: 12 with --tiny, else the "
                                                                   "model's limit)")
    ap.add_argument("--torch-threads", type=int, default=1, help="torch threads per worker (default 1)")
    ap.add_argument("--worker-nice", type=int, default=0,
                    help="niceness added to the workers (e.g. 10: the API keeps the CPU it needs to answer)")
    ap.add_argument("--poll-interval", type=float, default=0.05, help="seconds between the poller's GETs")
    ap.add_argument("--json", action="store_true", help="print every report as JSON")
    args = ap.parse_args()
    setups = [tuple(int(x) for x in (c.split("x") + ["1"])[:2]) for c in args.workers.split(",")]
    work = Path(tempfile.mkdtemp(prefix="fastmesh-throughput-"))
    weights = args.weights
    if args.tiny:
        from fastmesh.pipeline import Pipeline

        weights = str(work / "weights")
        Pipeline.random("tiny", seed=0).save(weights)
    else:
        from fastmesh.pipeline import default_weights_dir

        root = Path(weights) if weights else default_weights_dir()
        if not (root / "vertex" / "model.safetensors").exists():
            print(f"throughput: no weights in {root}; pass --weights DIR or --tiny", file=sys.stderr)
            return 2
    max_vertices = args.max_vertices or (12 if args.tiny else None)
    inputs = Path(args.inputs) if args.inputs else make_inputs(work)
    sample = sorted(p for p in inputs.iterdir() if p.is_file())[0]

    redis_server = RedisServer()
    s = Settings(redis_url=redis_server.url, weights=weights, torch_threads=args.torch_threads,
                 rate_limit_per_minute=0, submit_rate_limit_per_minute=0, max_queue_depth=10_000)
    print(f"[throughput] redis {redis_server.url}, logs and inputs in {work}", file=sys.stderr)
    api = ApiProcess(s, log_path=work / "api.log").wait_ready()
    workers: list[WorkerProcess] = []
    rows, reports = [], {}
    params = {"max_vertices": str(max_vertices)} if max_vertices else {}
    try:
        for k, batch in setups:
            while workers:  # each setup starts its own workers: the batch size is a worker's setting
                workers.pop().stop()
            for i in range(k):
                workers.append(WorkerProcess(s, f"bench-w{i + 1}", work / f"w{i + 1}-{k}x{batch}.log",
                                             FASTMESH_MAX_BATCH=str(batch)))
            for w in workers:
                w.wait_ready(300)
                if args.worker_nice:
                    os.setpriority(os.PRIO_PROCESS, w.pid, os.getpriority(os.PRIO_PROCESS, w.pid) + args.worker_nice)
            users = args.concurrency or 2 * k * batch + 2
            # Warm-up: the first jobs of a process pay torch's lazy initialisation (and the decoder's graph of
            # each batch size).
            run(LoadConfig(url=api.url, inputs=[inputs], concurrency=k * batch, jobs=k * batch, grace=args.grace,
                           params=params))
            print(f"[throughput] {k} worker(s) x {batch} job(s), {users} users, {args.duration:g} s ...",
                  file=sys.stderr)
            poll = subprocess.Popen([sys.executable, __file__, "--poll-only", api.url, str(args.duration),
                                     str(args.poll_interval), str(sample), json.dumps(params)],
                                    stdout=subprocess.PIPE, text=True)
            rep = run(LoadConfig(url=api.url, inputs=[inputs], concurrency=users, duration=args.duration,
                                 grace=args.grace, params=params))
            out, _ = poll.communicate(timeout=args.duration + args.grace + 60)
            rep["poll"] = json.loads(out)
            reports[f"{k}x{batch}"] = rep
            rows.append((f"{k}x{batch}", users, rep))
    finally:
        for w in workers:
            w.stop()
        api.stop()
        redis_server.stop()
    if args.json:
        print(json.dumps({str(k): r for k, r in reports.items()}, indent=2))
    print(table(rows, "tiny random model" if args.tiny else (weights or "shipped weights"), max_vertices,
                args.worker_nice))
    return 1 if any(r["jobs"]["lost"] for r in reports.values()) else 0


def table(rows: list[tuple[str, int, dict]], model: str, max_vertices: int | None, nice: int = 0) -> str:
    head = (f"model: {model}; max_vertices: {max_vertices or 'model limit'}; cores: {os.cpu_count()}; "
            f"worker nice +{nice}; load average {os.getloadavg()[0]:.1f}\n"
            f"{'workers':>7} {'users':>5} {'jobs':>5} {'fail':>4} {'jobs/min':>9} "
            f"{'e2e p50':>8} {'e2e p95':>8} {'e2e p99':>8} "
            f"{'queue p50':>9} {'queue p95':>9} {'poll p50':>9} {'poll p99':>9} {'lost':>4} {'http err':>8}\n"
            f"{'':>7} {'':>5} {'':>5} {'':>4} {'':>9} {'s':>8} {'s':>8} {'s':>8} {'s':>9} {'s':>9} {'ms':>9} {'ms':>9}")
    lines = [head]
    for k, users, r in rows:
        e, q, p = r["end_to_end_s"], r["queue_wait_s"], r["poll"]["ms"]
        j = r["jobs"]
        lines.append(f"{k:>7} {users:>5} {j['succeeded']:>5} {j['failed']:>4} {r['jobs_per_minute']:>9.1f} "
                     f"{e['p50'] or 0:>8.2f} {e['p95'] or 0:>8.2f} {e['p99'] or 0:>8.2f} {q['p50'] or 0:>9.2f} "
                     f"{q['p95'] or 0:>9.2f} {p['p50'] or 0:>9.2f} {p['p99'] or 0:>9.2f} {r['jobs']['lost']:>4} "
                     f"{sum(r['http_errors'].values()):>8}")
    base = rows[0][2]["jobs_per_minute"]
    for name, _, r in rows[1:] if base else []:
        lines.append(f"jobs/min of {name} vs {rows[0][0]} (workers x jobs each): {r['jobs_per_minute'] / base:.2f}x")
    return "\n".join(lines)


if __name__ == "__main__":
    if len(sys.argv) == 7 and sys.argv[1] == "--poll-only":  # the poller, as its own process
        print(json.dumps(poller(sys.argv[2], float(sys.argv[3]), float(sys.argv[4]), sys.argv[5],
                                json.loads(sys.argv[6]))))
        sys.exit(0)
    sys.exit(main())
