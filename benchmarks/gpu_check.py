"""The device check (``make gpu-check``): on a machine with one CUDA GPU and PyTorch, given this repository, it
installs what it lacks, runs the GPU tests and a throughput benchmark, and ends with one JSON line.  Without CUDA
the same runs on the CPU with fewer runs.

    python benchmarks/gpu_check.py

1. Installs.  PyTorch must be there.  Of the rest the check needs (numpy, scipy, trimesh, safetensors,
   mapbox-earcut, fast-simplification, pytest and its dependencies) what does not import is installed into
   ``.gpu-check/site`` (``pip --target``, nothing else of the environment changes): from ``./wheels`` alone when
   that folder exists (a machine with no network: ``pip install --no-index --find-links wheels``), else from the
   package index.  To fill ``wheels/`` on a machine with a network, for the GPU machine's Python (here 3.12) and
   what it lacks::

       python -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \\
           --platform manylinux2014_x86_64 --platform manylinux_2_28_x86_64 -d wheels \\
           trimesh mapbox-earcut fast-simplification

2. ``pytest -m gpu`` over the test files that hold GPU tests (``tests/test_gpu.py``, ``tests/test_static_decode.py``):
   CUDA and CPU results of the same quality, ``FASTMESH_GPU_CHECK_RUNS`` generate runs on varied inputs with no
   failure (default 100 on CUDA, 3 on a CPU), a batch of jobs equal to the jobs one by one, the captured decode
   step equal to the eager one.
3. The throughput benchmark on the same device: a result of about 500 vertices end to end (``p50_s_500v``), the
   decoder's steps per second on one sequence, jobs per minute one by one and batched (``Pipeline.generate_batch``;
   null where the pipeline has no batch API).
4. One JSON line: device, runs, failures, p50_s and p95_s (of the runs of 2), p50_s_500v, decode_steps_per_s,
   jobs_per_min_batched, jobs_per_min_single.  The exit status is 1 when a test failed or a run failed.
"""

from __future__ import annotations

import importlib
import importlib.util
import json
import logging
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
WORK = REPO / ".gpu-check"
SITE = WORK / "site"
RECORD = WORK / "runs.json"
WHEELS = REPO / "wheels"
# module -> distribution: what the pipeline and its tests import beyond PyTorch (and PyTorch's own dependencies)
NEEDS = {"numpy": "numpy", "scipy": "scipy", "trimesh": "trimesh", "safetensors": "safetensors",
         "mapbox_earcut": "mapbox-earcut", "fast_simplification": "fast-simplification", "pytest": "pytest",
         "iniconfig": "iniconfig", "packaging": "packaging", "pluggy": "pluggy", "pygments": "pygments"}
CUDA_SIZES = {"runs": 100, "jobs": 16, "runs_500v": 5, "decode_inputs": 3}
CPU_SIZES = {"runs": 3, "jobs": 2, "runs_500v": 1, "decode_inputs": 1}


def install() -> None:
    """Install the missing distributions of ``NEEDS`` into ``SITE`` and put it on the path."""
    if importlib.util.find_spec("torch") is None:
        sys.exit("gpu-check: PyTorch is missing; install the build for this machine's CUDA (https://pytorch.org)")
    missing = sorted({dist for module, dist in NEEDS.items() if importlib.util.find_spec(module) is None})
    if missing:
        source = ["--no-index", "--find-links", str(WHEELS)] if WHEELS.is_dir() else []
        print(f"gpu-check: installing {' '.join(missing)} into {SITE}"
              f" {'from ' + str(WHEELS) if source else 'from the package index'}", flush=True)
        cmd = [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-compile", "--upgrade",
               "--target", str(SITE), *source, *missing]
        if subprocess.run(cmd).returncode != 0:
            sys.exit(f"gpu-check: could not install {' '.join(missing)}" + (
                f"; fill {WHEELS} as this script's docstring says" if source else ""))
    sys.path[:0] = [str(SITE), str(REPO), str(REPO / "tests")]
    importlib.invalidate_caches()


def run_tests() -> int:
    """``pytest -m gpu`` over the test files that hold GPU tests; its exit status."""
    files = sorted(str(p.relative_to(REPO)) for p in (REPO / "tests").glob("test_*.py")
                   if "mark.gpu" in p.read_text())
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(SITE), str(REPO), os.environ.get("PYTHONPATH", "")]),
           "FASTMESH_GPU_CHECK_RECORD": str(RECORD)}
    RECORD.unlink(missing_ok=True)
    cmd = [sys.executable, "-m", "pytest", "-q", "-m", "gpu", "-p", "no:cacheprovider", *files]
    print("gpu-check:", " ".join(cmd[2:]), flush=True)
    return subprocess.run(cmd, cwd=REPO, env=env).returncode


def _quantile(values: list[float], q: float) -> float | None:
    if not values:
        return None
    import numpy as np

    return round(float(np.quantile(values, q)), 3)


def benchmark(sizes: dict) -> dict:
    """p50_s_500v, decode_steps_per_s and jobs per minute on the device the tests used."""
    import torch
    from decode_paths import encoded, shapes
    from gpu_inputs import five_hundred, varied
    from test_gpu import DEVICE, run

    from fastmesh.models.generate import generate
    from fastmesh.params import GenerateParams
    from fastmesh.pipeline import Pipeline

    pipe = Pipeline.from_pretrained(device=DEVICE)
    out = {}
    cuda = DEVICE == "cuda"
    if cuda:  # warm-up: graph captures, first allocations and kernel choices
        pipe.generate(*five_hundred(1, seed=99)[0][1:])
    times = [run(pipe, *x)["s"] for x in five_hundred(sizes["runs_500v"])]
    out["p50_s_500v"] = _quantile(times, 0.5)
    params = GenerateParams(seed=0, candidates=1)
    cfg = params.sampling(pipe.max_vertices)
    steps, seconds = 0, 0.0
    for i, shape in enumerate(list(shapes().values())[:sizes["decode_inputs"]]):
        prefix, evidence = encoded(pipe, shape, params)
        if cuda and i == 0:  # the capture of a batch of one
            generate(pipe.decoder, prefix, cfg, evidence=evidence)
        if cuda:
            torch.cuda.synchronize()
        t = time.perf_counter()
        seqs = generate(pipe.decoder, prefix, cfg, evidence=evidence)
        if cuda:
            torch.cuda.synchronize()
        seconds += time.perf_counter() - t
        steps += len(seqs[0]) - 1
    out["decode_steps_per_s"] = round(steps / seconds, 1)
    jobs = varied(sizes["jobs"], seed=9)
    t = time.perf_counter()
    records = [run(pipe, *job) for job in jobs]
    out["jobs_per_min_single"] = round(60 * len(jobs) / (time.perf_counter() - t), 2)
    out["benchmark_failures"] = [f"{r['name']}: {r.get('error', 'no faces')}" for r in records if not r["ok"]]
    out["jobs_per_min_batched"] = None
    if hasattr(pipe, "generate_batch"):
        t = time.perf_counter()
        pipe.generate_batch([s for _, s, _ in jobs], [p for _, _, p in jobs])
        out["jobs_per_min_batched"] = round(60 * len(jobs) / (time.perf_counter() - t), 2)
    shapes_seen = getattr(pipe.decoder, "_batches", {})
    print(f"gpu-check: decoder {pipe.info()['decoder']}, {sum(b.graph is not None for b in shapes_seen.values())} of"
          f" {len(shapes_seen)} batch shapes kept captured as CUDA graphs,"
          f" {sum(b.fused is not None for b in shapes_seen.values())} with the network's step compiled", flush=True)
    return out


def device_name() -> str:
    import torch

    if torch.cuda.is_available():
        return torch.cuda.get_device_name(0)
    return f"cpu ({os.cpu_count()} cores)"


def main() -> int:
    t0 = time.perf_counter()
    WORK.mkdir(exist_ok=True)
    logging.basicConfig(level=logging.WARNING, format="gpu-check: %(name)s: %(message)s")  # e.g. a failed capture
    install()
    import torch

    cuda = torch.cuda.is_available()
    sizes = CUDA_SIZES if cuda else CPU_SIZES
    os.environ.setdefault("FASTMESH_GPU_CHECK_RUNS", str(sizes["runs"]))
    status = run_tests()
    runs = json.loads(RECORD.read_text())["runs"] if RECORD.exists() else []
    ok_s = [r["s"] for r in runs if r["ok"]]
    result = {"device": device_name(), "runs": len(runs), "failures": sum(not r["ok"] for r in runs),
              "p50_s": _quantile(ok_s, 0.5), "p95_s": _quantile(ok_s, 0.95)}
    try:
        result.update(benchmark(sizes))
    except Exception as e:  # noqa: BLE001 - the line still comes out, with what was measured
        print(f"gpu-check: benchmark failed: {type(e).__name__}: {e}", flush=True)
        status = status or 1
    keys = ("device", "runs", "failures", "p50_s", "p95_s", "p50_s_500v", "decode_steps_per_s",
            "jobs_per_min_batched", "jobs_per_min_single")
    for failure in result.get("benchmark_failures", []):  # a throughput job that failed is a failure too
        print(f"gpu-check: benchmark job failed: {failure}", flush=True)
        status = status or 1
    print(f"gpu-check: {time.perf_counter() - t0:.0f} s in all", flush=True)
    print(json.dumps({k: result.get(k) for k in keys}), flush=True)
    return 1 if status or result["failures"] or not runs else 0


if __name__ == "__main__":
    sys.exit(main())
