"""Jobs per minute of N worker processes sharing one device: how many GPU workers a machine should run.

    python benchmarks/gpu_workers.py [--processes 1 4 8 16] [--duration 20] [--device cuda] [--json]

A GPU worker's job spends most of its time in CPU stages (sampling, the face stage's geometry), so one process
leaves the GPU idle; several processes, each with one torch thread and its own CUDA context, overlap them.  Each
process loads the shipped pipeline, warms it up (graph captures), waits for the others, then generates the
varied inputs of ``tests/gpu_inputs.py`` (point clouds, artist meshes, posed primitives, each with its own
parameters) in turn for ``--duration`` seconds.  Jobs per minute counts the jobs finished over the time the
last one finished; latency is each job's seconds.  No Redis and no service: the pipeline's ceiling, which
``benchmarks/throughput.py`` measures through the whole service where its dependencies are installed.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def _worker(rank: int, n: int, device: str, jobs: list, duration: float, ready, start, results) -> None:
    sys.path[:0] = [str(REPO), str(REPO / "tests")]
    import torch

    from fastmesh.pipeline import Pipeline

    torch.set_num_threads(1)
    pipe = Pipeline.from_pretrained(device=device, threads=1)
    for _, shape, params in jobs[:2]:  # the batch shapes of one and two candidates: captured before timing
        try:
            pipe.generate(shape, params)
        except Exception:  # noqa: BLE001 - a warm-up failure shows again, counted, in the timed loop
            pass
    ready.put(rank)
    start.wait()
    t0, done, i = time.perf_counter(), [], rank
    while time.perf_counter() - t0 < duration:
        name, shape, params = jobs[i % len(jobs)]
        t = time.perf_counter()
        try:
            pipe.generate(shape, params)
            error = None
        except Exception as e:  # noqa: BLE001 - counted as a failure, reported with its input
            error = f"{name}: {type(e).__name__}: {e}"[:400]
        done.append((time.perf_counter() - t, error, time.perf_counter() - t0))
        i += n
    results.put(done)


def measure(n: int, device: str, jobs: list, duration: float) -> dict:
    """Jobs per minute and latency of ``n`` processes for ``duration`` seconds."""
    ctx = mp.get_context("spawn")  # CUDA cannot be used in a forked child
    ready, results, start = ctx.Queue(), ctx.Queue(), ctx.Event()
    procs = [ctx.Process(target=_worker, args=(r, n, device, jobs, duration, ready, start, results))
             for r in range(n)]
    for p in procs:
        p.start()
    for _ in procs:
        ready.get()
    start.set()
    runs = [x for _ in procs for x in results.get()]
    for p in procs:
        p.join()
    seconds = [s for s, _, _ in runs]
    errors = sorted({e for _, e, _ in runs if e})
    return {"processes": n, "jobs": len(runs), "failures": sum(e is not None for _, e, _ in runs), "errors": errors[:5],
            "jobs_per_min": round(60 * len(runs) / max(end for _, _, end in runs), 1),
            "p50_s": round(float(np.median(seconds)), 3), "p95_s": round(float(np.quantile(seconds, 0.95)), 3)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--processes", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--duration", type=float, default=20.0, help="seconds of jobs per process count")
    ap.add_argument("--device", default=None, help="cuda or cpu (default: cuda where there is one)")
    ap.add_argument("--jobs", type=int, default=16, help="distinct inputs, taken in turn")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    sys.path[:0] = [str(REPO), str(REPO / "tests")]
    import torch
    from gpu_inputs import varied

    device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    jobs = varied(args.jobs, seed=9)
    rows = []
    for n in args.processes:
        rows.append({"device": device, **measure(n, device, jobs, args.duration)})
        print(json.dumps(rows[-1]) if args.json else
              f"{n:3d} processes: {rows[-1]['jobs_per_min']:7.1f} jobs/min, p50 {rows[-1]['p50_s']} s, "
              f"p95 {rows[-1]['p95_s']} s, {rows[-1]['failures']} failures of {rows[-1]['jobs']}"
              + "".join(f"\n    {e}" for e in rows[-1]["errors"]), flush=True)


if __name__ == "__main__":
    main()
