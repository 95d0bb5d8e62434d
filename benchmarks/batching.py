"""Jobs one by one vs batched in one process (``Pipeline.generate_batch``), on the same inputs: seconds of CPU and
of wall clock per job, and whether each batched result equals the one made alone.

    python benchmarks/batching.py                        # 8 point clouds of tests/data/corpus, batches of 4
    python benchmarks/batching.py --inputs DIR --limit 12 --batch 4

The jobs run a chunk of ``--batch`` at a time, one by one and batched in turn.  CPU seconds (the process's
own, ``time.process_time``) are what a saturated one-thread worker turns into jobs per minute, and they move
less than wall seconds with what else the machine runs.  Default settings (2 candidates per job); torch and
ONNX Runtime on one thread, as a worker runs them.  Prints one JSON line.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

CORPUS = Path(__file__).resolve().parents[1] / "tests" / "data" / "corpus"


def shapes(inputs: str | None, limit: int) -> list:
    """The first ``limit`` inputs of ``inputs`` (sorted), or point clouds (8,192 samples with normals) of the
    test corpus's base meshes (no poses)."""
    from fastmesh.shapes.io import load_shape, sample_surface
    from fastmesh.shapes.shape import SUPPORTED_FORMATS, Shape

    if inputs:
        files = sorted(f for f in Path(inputs).iterdir() if f.suffix.lower().lstrip(".") in SUPPORTED_FORMATS)
        return [load_shape(f) for f in files[:limit]]
    out = []
    for f in sorted(p for p in CORPUS.glob("*/*.ply") if not p.parent.name.endswith("-poses"))[:limit]:
        pts, nrm = sample_surface(load_shape(f), 8192, seed=0)
        out.append(Shape(vertices=pts.astype(np.float64), normals=nrm.astype(np.float64)))
    return out


def timed(run) -> tuple[list, float, float]:
    cpu, wall = time.process_time(), time.perf_counter()
    out = run()
    return out, time.process_time() - cpu, time.perf_counter() - wall


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--inputs", default=None, metavar="DIR", help="point clouds or meshes (default: the corpus's)")
    ap.add_argument("--limit", type=int, default=8, help="inputs used (default 8)")
    ap.add_argument("--batch", type=int, default=4, help="jobs per batch (default 4)")
    args = ap.parse_args()
    from fastmesh.params import GenerateParams
    from fastmesh.pipeline import Pipeline

    pipe = Pipeline.from_pretrained(threads=1)
    jobs = shapes(args.inputs, args.limit)
    params = [GenerateParams(seed=i) for i in range(len(jobs))]
    # Warm-up: first calls, and the ONNX decoder's graph of every row count a batch can start with (exported on
    # first use otherwise, inside the timed runs).
    pipe.generate(jobs[0], params[0])
    for rows in range(1, 2 * args.batch + 1):
        getattr(pipe.decoder, "_session", lambda b: None)(rows)
    # Chunk by chunk, one by one and batched in turn (ABBA): the machine's drift falls on both alike.
    alone, batched, cpu1, wall1, cpub, wallb = [], [], 0.0, 0.0, 0.0, 0.0
    for k, i in enumerate(range(0, len(jobs), args.batch)):
        chunk, ps = jobs[i:i + args.batch], params[i:i + args.batch]
        for mode in ("alone", "batched") if k % 2 == 0 else ("batched", "alone"):
            if mode == "alone":
                out, cpu, wall = timed(lambda c=chunk, q=ps: [pipe.generate_batch([s], [p])[0]
                                                            for s, p in zip(c, q, strict=True)])
                alone, cpu1, wall1 = alone + out, cpu1 + cpu, wall1 + wall
            else:
                out, cpu, wall = timed(lambda c=chunk, q=ps: pipe.generate_batch(c, q))
                batched, cpub, wallb = batched + out, cpub + cpu, wallb + wall
    same = sum(isinstance(a, Exception) and type(a) is type(b) or not isinstance(a, Exception) and
               np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces)
               for a, b in zip(alone, batched, strict=True))
    n = len(jobs)
    print(json.dumps({
        "jobs": n, "batch": args.batch, "same_results": same,
        "decoded": sum(not isinstance(a, Exception) and a.tokens > 0 for a in alone),
        "one_by_one": {"cpu_s_per_job": round(cpu1 / n, 3), "wall_s_per_job": round(wall1 / n, 3),
                       "jobs_per_cpu_minute": round(60 * n / cpu1, 2)},
        "batched": {"cpu_s_per_job": round(cpub / n, 3), "wall_s_per_job": round(wallb / n, 3),
                    "jobs_per_cpu_minute": round(60 * n / cpub, 2)},
        "batched_vs_one_by_one_cpu": round(cpu1 / cpub, 3),
        "vertices_stage_s_per_job": {"one_by_one": round(sum(a.timings["vertices"] for a in alone
                                                             if not isinstance(a, Exception)) / n, 3),
                                     "batched": round(sum(b.timings["vertices"] for b in batched
                                                          if not isinstance(b, Exception)) / n, 3)},
    }))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
