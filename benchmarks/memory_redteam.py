"""Peak and after-case memory of the API, its child processes, the worker and Redis under the hostile inputs of
a red-team re-test (amplifying glTF accessors, a burst of ``input.ply``, unspaced OBJ faces, glTF JSON of empty
containers, polygon fans, one-vertex OFF faces, a 500,000-point cloud for the worker).

    python benchmarks/memory_redteam.py [--weights DIR] [--skip-worker] [--markdown]

Starts its own redis-server, the API as ``make run`` serves it (uvicorn subprocess, ``service.http:Protocol``)
and one ``fastmesh-worker`` (shipped weights unless ``--weights``), samples each process's resident memory every
20 ms, and prints one line per case: the answers, the API's RSS before, at its peak and 1 s after, the peak of
the API's child processes (parsing, rendering), the worker's and Redis's peaks.  ``--markdown`` prints the
cases as a Markdown table at the end (summarised in docs/results.md).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import numpy as np
import trimesh
from attack_memory import Peak, npy, rss_mib

from fastmesh_jobs.runtime import wait_for
from fastmesh_jobs.settings import Settings
from service.processes import ApiProcess, RedisServer, WorkerProcess, free_port

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from hostile import (  # noqa: E402
    gltf_empty_nodes,
    obj_unspaced_faces,
    off_one_vertex_faces,
    ply_fans,
    strided_accessor_glb,
)

SETTLE_SECONDS = 1.0  # after a case, before its "after" is read


def post(url: str, name: str, data: bytes, **fields) -> httpx.Response:
    return httpx.post(f"{url}/v1/jobs", files={"file": (name, data)}, data={k: str(v) for k, v in fields.items()},
                      timeout=600)


def grid_ply(n: int = 670) -> bytes:
    """A wavy n x n grid: 2 (n - 1)^2 faces (895,122 for 670), a 17 MB binary PLY."""
    u, v = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
    verts = np.stack([u.ravel(), v.ravel(), 0.05 * np.sin(8 * u.ravel()) * np.cos(8 * v.ravel())], 1)
    i = np.arange(n * n).reshape(n, n)[:-1, :-1].ravel()
    faces = np.concatenate([np.stack([i, i + 1, i + n], 1), np.stack([i + 1, i + n + 1, i + n], 1)])
    return trimesh.Trimesh(verts, faces, process=False).export(file_type="ply")


def gltf_nested_extras(megabytes: int) -> bytes:
    n = megabytes * 1024 * 1024 // 3
    return b'{"asset":{"version":"2.0"},"extras":[' + b"[]," * n + b"[]]}"


def cases(url: str) -> list[tuple[str, callable]]:
    """``(name, run)``: ``run()`` makes the requests and returns ``{answer: count}``."""

    def one(name: str, data: bytes):
        def run():
            r = post(url, name, data)
            return {f"{r.status_code} {r.json().get('error', {}).get('code', '')}".strip(): 1}
        return run

    def input_ply_burst():
        r = post(url, "grid.ply", grid_ply())
        assert r.status_code == 202, r.text
        target = f"{url}/v1/jobs/{r.json()['id']}/input.ply?points=200000"
        with ThreadPoolExecutor(40) as pool:
            codes = list(pool.map(lambda _: httpx.get(target, timeout=600).status_code, range(40)))
        httpx.delete(f"{url}/v1/jobs/{r.json()['id']}")  # the worker is measured on its own case
        return {str(c): codes.count(c) for c in sorted(set(codes))}

    return [
        ("N1 GLB, 16 MAT4 accessors on a 1 MB view, byteStride 1", one("amp.glb", strided_accessor_glb())),
        ("N2 40 x input.ply?points=200000 of an 895k-face input", input_ply_burst),
        ("N3 OBJ, 9M `f1 2 3` lines (61.5 MB)", one("f.obj", obj_unspaced_faces(9_000_000))),
        ("N4 glTF, 20M `{}` nodes (60 MB)", one("j.gltf", gltf_empty_nodes(20_971_520))),
        ("N4 glTF, 16 MB of `[]` in extras", one("e.gltf", gltf_nested_extras(16))),
        ("N5 PLY, 58,000 faces of 255 corners (57 MB)", one("fan.ply", ply_fans(58_000))),
        ("N5 OFF, 2M faces on one vertex (15 MB)", one("one.off", off_one_vertex_faces(2_000_000))),
    ]


def measure(name: str, run, api: ApiProcess, redis_pid: int, worker_pid: int | None) -> dict:
    with Peak(api.pid) as a, Peak(redis_pid) as r, Peak(worker_pid or api.pid) as w:
        t0 = time.perf_counter()
        answers = run()
        took = time.perf_counter() - t0
        time.sleep(SETTLE_SECONDS)
    return {"case": name, "answers": answers, "seconds": round(took, 1), "api_before_mib": round(a.before),
            "api_peak_mib": round(a.peak), "api_after_mib": round(rss_mib(api.pid)),
            "children_peak_mib": round(a.kids), "worker_peak_mib": round(w.peak) if worker_pid else None,
            "redis_peak_mib": round(r.peak)}


def worker_cases(url: str, api: ApiProcess, redis_pid: int, worker: WorkerProcess) -> list[dict]:
    """The worker's peak on the largest inputs of each kind the limits let through."""
    p = np.random.default_rng(0).normal(size=(500_000, 3))
    points = npy(p / np.linalg.norm(p, axis=1, keepdims=True) * [1.0, 0.7, 0.4])  # an ellipsoid's surface

    def job(name: str, data: bytes):
        def run():
            job_id = post(url, name, data, candidates=1).json()["id"]
            final = wait_for(lambda: (j := httpx.get(f"{url}/v1/jobs/{job_id}").json())["status"]
                             in ("succeeded", "failed", "cancelled") and j, 1200, 0.2, what="the job")
            return {f"{final['status']} {(final.get('error') or {}).get('code', '')}".strip(): 1}
        return run

    return [measure("N8 worker, 500,000-point .npy of an ellipsoid (normals estimated), candidates=1",
                    job("big.npy", points), api, redis_pid, worker.pid),
            measure("worker, an 895k-face mesh (a 17 MB PLY), candidates=1", job("grid.ply", grid_ply()), api,
                    redis_pid, worker.pid)]


def markdown(rows: list[dict]) -> str:
    out = ["| case | answers | s | API before / peak / after MiB | API children peak MiB | worker peak MiB "
           "| Redis peak MiB |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        answers = ", ".join(f"{n} x {k}" for k, n in r["answers"].items())
        worker = r["worker_peak_mib"] if r["worker_peak_mib"] is not None else "-"
        out.append(f"| {r['case']} | {answers} | {r['seconds']} | {r['api_before_mib']} / {r['api_peak_mib']} / "
                   f"{r['api_after_mib']} | {r['children_peak_mib']} | {worker} | {r['redis_peak_mib']} |")
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--weights", default=None, help="weights folder of the worker (default: shipped)")
    ap.add_argument("--skip-worker", action="store_true", help="the API cases only (no model needed)")
    ap.add_argument("--markdown", action="store_true", help="print the results as a markdown table at the end")
    args = ap.parse_args()
    redis_server = RedisServer(directory=tempfile.mkdtemp(prefix="fastmesh-redteam-"), appendonly=True)
    settings = Settings(redis_url=redis_server.url, weights=args.weights, rate_limit_per_minute=0,
                        submit_rate_limit_per_minute=0, port=free_port())
    url = f"http://127.0.0.1:{settings.port}"
    api = ApiProcess(settings, port=settings.port)
    worker = None
    rows = []
    try:
        api.wait_ready()
        if not args.skip_worker:
            worker = WorkerProcess(settings, f"redteam-{os.getpid()}").wait_ready(300)
        for name, run in cases(url):
            rows.append(measure(name, run, api, redis_server.proc.pid, worker.pid if worker else None))
            print(json.dumps(rows[-1]), flush=True)
        if worker is not None:
            for row in worker_cases(url, api, redis_server.proc.pid, worker):
                rows.append(row)
                print(json.dumps(row), flush=True)
    finally:
        api.stop()
        if worker is not None:
            worker.stop()
        redis_server.stop()
    if args.markdown:
        print(markdown(rows))


if __name__ == "__main__":
    main()
