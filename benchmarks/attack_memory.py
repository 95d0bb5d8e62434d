"""Peak memory of the API and the worker under four attacks: previews, glTF instancing, parsing, zero normals.

    python benchmarks/attack_memory.py [--weights DIR] [--skip-worker]

Starts its own redis-server, the API (uvicorn subprocess) and one ``fastmesh-worker`` (shipped weights
unless ``--weights``), samples each process's resident memory every 20 ms, and prints one line per
attack (baseline and peak RSS in MiB, answers, latencies) and one JSON object at the end:

1. previews: 40 concurrent uncached ``preview.png`` requests (sizes 200-958) of a dense input mesh,
   then three bursts of 20; ``GET /v1/jobs/{id}`` and ``/healthz`` timed meanwhile.  The render
   processes the API may use are reported separately (``render_children``).
2. glTF instancing: a ~150 KB GLB whose 1,200 nodes show one 642-vertex mesh.
3. parsing: 6 concurrent 500,000-point ``.npy`` uploads (the default limit).
4. zero normals: 500 points of a cube with all normals ``0 0 0``, and the same points without normals
   (the worker's peak for each job).

Only HTTP and the processes of :mod:`service.processes` are used, so the same script measures another
checkout that has them (``PYTHONPATH=/path/to/other/checkout python benchmarks/attack_memory.py``).
"""

from __future__ import annotations

import argparse
import io
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import numpy as np
import trimesh

from fastmesh_jobs.runtime import wait_for
from fastmesh_jobs.settings import Settings
from service.processes import ApiProcess, RedisServer, WorkerProcess, free_port

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from hostile import instanced_glb  # noqa: E402


def rss_mib(pid: int) -> float:
    """Resident memory of ``pid`` in MiB (0 once it is gone)."""
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return 0.0


def children(pid: int) -> list[int]:
    out = []
    try:
        for task in os.listdir(f"/proc/{pid}/task"):
            with open(f"/proc/{pid}/task/{task}/children") as f:
                out += [int(c) for c in f.read().split()]
    except OSError:
        pass
    return out


class Peak:
    """Samples the RSS of a process (and, separately, of its children) every ``interval`` s while active."""

    def __init__(self, pid: int, interval: float = 0.02):
        self.pid, self.interval = pid, interval
        self.peak = self.kids = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        while not self._stop.is_set():
            self.peak = max(self.peak, rss_mib(self.pid))
            self.kids = max(self.kids, sum(rss_mib(c) for c in children(self.pid)))
            self._stop.wait(self.interval)

    def __enter__(self):
        self.before = rss_mib(self.pid)
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self.after = rss_mib(self.pid)


def npy(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, arr)
    return buf.getvalue()




def cube_points(n: int = 500, normals: bool = False) -> bytes:
    rng = np.random.default_rng(0)
    p = rng.uniform(-1, 1, size=(n, 3))
    axis = rng.integers(0, 3, n)
    p[np.arange(n), axis] = np.sign(rng.uniform(-1, 1, n))  # onto the cube's faces
    rows = np.hstack([p, np.zeros_like(p)]) if normals else p
    buf = io.StringIO()
    np.savetxt(buf, rows, fmt="%.6f")
    return buf.getvalue().encode()


def post(url: str, name: str, data: bytes, **fields) -> httpx.Response:
    return httpx.post(f"{url}/v1/jobs", files={"file": (name, data)}, data={k: str(v) for k, v in fields.items()},
                      timeout=300)


def attack_previews(url: str, api: int, out: dict) -> None:
    mesh = trimesh.creation.icosphere(7)  # 327,680 faces: a dense scan-like input
    r = post(url, "dense.ply", mesh.export(file_type="ply"))
    job_id = r.json()["id"]
    rng = np.random.default_rng(0)
    lat = {"job": [], "healthz": []}
    stop = threading.Event()

    def watch():
        # Timed by curl, in its own process: this one's 40 client threads would delay a Python timer.
        while not stop.is_set():
            for name, path in (("job", f"/v1/jobs/{job_id}"), ("healthz", "/healthz")):
                took = subprocess.run(["curl", "-s", "-o", "/dev/null", "-w", "%{time_total}", url + path],
                                      capture_output=True, text=True, timeout=120).stdout
                lat[name].append(float(took))
            time.sleep(0.1)

    def get(size):
        t0 = time.perf_counter()
        resp = httpx.get(f"{url}/v1/jobs/{job_id}/preview.png", params={"size": int(size)}, timeout=300)
        return resp.status_code, time.perf_counter() - t0

    watcher = threading.Thread(target=watch, daemon=True)
    with Peak(api) as p:
        watcher.start()
        codes, steps = [], []
        for n in (40, 20, 20, 20):
            with ThreadPoolExecutor(n) as pool:
                got = list(pool.map(get, rng.integers(200, 959, n)))
            codes += [c for c, _ in got]
            steps.append(round(rss_mib(api)))
        stop.set()
        watcher.join()
    httpx.delete(f"{url}/v1/jobs/{job_id}")
    out["1_previews"] = {"api_before_mib": round(p.before), "api_peak_mib": round(p.peak),
                         "api_after_mib": round(p.after), "api_after_each_burst_mib": steps,
                         "render_children_peak_mib": round(p.kids),
                         "answers": {str(c): codes.count(c) for c in sorted(set(codes))},
                         "get_job_max_s": round(max(lat["job"]), 3), "healthz_max_s": round(max(lat["healthz"]), 3)}


def attack_gltf(url: str, api: int, out: dict) -> None:
    data = instanced_glb(1200)
    with Peak(api) as p:
        t0 = time.perf_counter()
        r = post(url, "instanced.glb", data)
        took = time.perf_counter() - t0
    out["2_gltf_instancing"] = {"upload_kb": round(len(data) / 1024), "api_before_mib": round(p.before),
                                "api_peak_mib": round(p.peak), "status": r.status_code, "seconds": round(took, 2),
                                "message": r.json().get("error", {}).get("message", "")[:120]}


def attack_parsing(url: str, api: int, out: dict) -> None:
    data = npy(np.random.default_rng(0).normal(size=(500_000, 3)))
    with Peak(api) as p, ThreadPoolExecutor(6) as pool:
        t0 = time.perf_counter()
        got = list(pool.map(lambda _: (post(url, "big.npy", data), time.perf_counter() - t0), range(6)))
    for r, _ in got:
        if r.status_code == 202:
            httpx.delete(f"{url}/v1/jobs/{r.json()['id']}")
    codes = [r.status_code for r, _ in got]
    out["3_parsing"] = {"api_before_mib": round(p.before), "api_peak_mib": round(p.peak),
                        "api_after_mib": round(p.after), "answers": {str(c): codes.count(c) for c in set(codes)},
                        "slowest_answer_s": round(max(t for _, t in got), 2)}


def attack_normals(url: str, worker: int, out: dict) -> None:
    res = {}
    for name, data in (("zero_normals", cube_points(normals=True)), ("no_normals", cube_points())):
        with Peak(worker) as p:
            job_id = post(url, "cube.xyz", data).json()["id"]
            final = wait_for(lambda job_id=job_id: (j := httpx.get(f"{url}/v1/jobs/{job_id}").json())["status"]
                             in ("succeeded", "failed", "cancelled") and j, 600, 0.2, what="the job")
        res[name] = {"worker_before_mib": round(p.before), "worker_peak_mib": round(p.peak),
                     "status": final["status"], "faces": (final.get("result") or {}).get("faces"),
                     "total_s": round(final["timings"]["total"] or 0, 1)}
    out["5_zero_normals"] = res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--weights", default=None, help="weights folder of the worker (default: shipped)")
    ap.add_argument("--skip-worker", action="store_true", help="attacks 1-3 only (no model needed)")
    args = ap.parse_args()
    workdir = tempfile.mkdtemp(prefix="fastmesh-attack-")
    redis_server = RedisServer(directory=workdir)
    settings = Settings(redis_url=redis_server.url, weights=args.weights, rate_limit_per_minute=0,
                        submit_rate_limit_per_minute=0, port=free_port())
    url = f"http://127.0.0.1:{settings.port}"
    api = ApiProcess(settings, port=settings.port, log_path="-")
    worker = None
    out: dict = {"python_path": os.environ.get("PYTHONPATH", "")}
    try:
        api.wait_ready()
        for attack in (attack_gltf, attack_parsing, attack_previews):
            known = set(out)
            attack(url, api.pid, out)
            print(json.dumps({k: out[k] for k in set(out) - known}), flush=True)
        if not args.skip_worker:
            worker = WorkerProcess(settings, f"attack-{os.getpid()}").wait_ready(300)
            attack_normals(url, worker.pid, out)
            print(json.dumps(out["5_zero_normals"]), flush=True)
    finally:
        api.stop()
        if worker is not None:
            worker.stop()
        redis_server.stop()
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
