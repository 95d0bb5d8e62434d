"""Peak memory and time of the face stage at N = 1000 / 2000 / 4000 vertices.

Each N runs in a fresh process so its peak resident set size (ru_maxrss) is its own.

Default: one face-model pass (default FaceModelConfig), random weights and random distinct
cells (memory and time do not depend on the values).

``--stage``: the whole face stage as the pipeline runs it, with the shipped face model and
settings (``fastmesh/weights``): network pass, prediction filtering, candidate triangles,
selection and hole filling.  The vertices are N distinct 7-bit cells on a sphere (a Fibonacci
lattice), the input 8192 samples of that sphere.  Targets: peak RSS < 2 GB, < 20 s on 2 threads.

    python benchmarks/face_memory.py [--sizes 1000 2000 4000] [--threads 1] [--masked] [--pair-chunk K]
    python benchmarks/face_memory.py --stage --threads 2 [--sizes 4000] [--filtering]

Prints one JSON line per N: baseline RSS after building the model, peak RSS during the
pass, seconds for the unmasked pass (and for a banded-mask pass with --masked); with --stage
seconds for the network with filtering and for the faces, the edge and face counts.
"""

from __future__ import annotations

import argparse
import subprocess
import sys

CHILD = r"""
import json, resource, sys, time
import numpy as np, torch
n, threads, masked, chunk = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3] == "1", int(sys.argv[4])
torch.set_num_threads(threads)
from fastmesh.models.face import FaceModel, FaceModelConfig
from fastmesh.tokenizer.grid import LEVELS
torch.manual_seed(0)
model = FaceModel(FaceModelConfig(**({"pair_chunk": chunk} if chunk else {}))).eval()
rng = np.random.default_rng(0)
q = np.zeros((0, 3), dtype=np.int64)
while len(q) < n:
    q = np.unique(np.concatenate([q, rng.integers(0, LEVELS, (n, 3))]), axis=0)
q = q[rng.permutation(len(q))[:n]]
pts = rng.uniform(-0.5, 0.5, (2048, 3)).astype(np.float32)
nrm = rng.normal(size=(2048, 3)).astype(np.float32)
def rss_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
base = rss_mb()
predict = model.predictor(q, pts, nrm)
t0 = time.perf_counter()
logits = predict(np.arange(n), None)
t_full = time.perf_counter() - t0
out = {"n": n, "threads": threads, "pair_chunk": model.cfg.pair_chunk,
       "baseline_rss_mb": round(base), "full_pass_s": round(t_full, 2)}
if masked:
    idx = np.arange(n)
    mask = np.abs(idx[:, None] - idx[None]) <= 64
    t0 = time.perf_counter()
    predict(idx, mask)
    out["masked_pass_s"] = round(time.perf_counter() - t0, 2)
out["peak_rss_mb"] = round(rss_mb())
out["logits_mb"] = round(logits.nbytes / 2**20)
print(json.dumps(out))
"""

STAGE = r"""
import json, resource, sys, time
import numpy as np, torch
n, threads, filtering = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3] == "1"
torch.set_num_threads(threads)
from fastmesh.faces import mesh_from_adjacency
from fastmesh.pipeline import Pipeline
from fastmesh.tokenizer import dequantize
from fastmesh.tokenizer.grid import LEVELS

def rss_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

def sphere(m):
    k = np.arange(m) + 0.5
    z, phi = 1 - 2 * k / m, np.pi * (1 + 5 ** 0.5) * k
    r = np.sqrt(1 - z ** 2)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)

m = n
mid = (LEVELS - 1) / 2  # the grid's centre, in cells
while True:  # n distinct cells of a sphere of radius 63.5 cells
    q = np.unique(np.clip(np.round(mid + mid * sphere(m) - 0.5), 0, LEVELS - 1).astype(np.int64), axis=0)
    if len(q) >= n:
        break
    m = int(m * 1.05) + 1
q = q[np.random.default_rng(0).permutation(len(q))[:n]]
pts = 0.5 * sphere(8192)
nrm = 2 * pts
pipe = Pipeline.from_pretrained(device="cpu")
base = rss_mb()
t0 = time.perf_counter()
n_fp = pipe.face.cfg.encoder.n_points
edges, logits = pipe.face.predict_edges(q, pts[:n_fp], nrm[:n_fp], filtering=pipe.filter_config if filtering else None,
                                        return_logits=True)
t1 = time.perf_counter()
v, f = mesh_from_adjacency(dequantize(q), edges, pipe.triangle_config, points=pts, logits=logits)
t2 = time.perf_counter()
print(json.dumps({"n": n, "threads": threads, "filtering": filtering, "selection": pipe.triangle_config.selection,
                  "baseline_rss_mb": round(base), "peak_rss_mb": round(rss_mb()),
                  "network_and_filtering_s": round(t1 - t0, 2), "faces_s": round(t2 - t1, 2),
                  "total_s": round(t2 - t0, 2), "edges": int(len(edges)), "faces": int(len(f))}))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 2000, 4000])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--masked", action="store_true", help="also time a pass with a band attention mask")
    ap.add_argument("--pair-chunk", type=int, default=0, help="override pair_chunk (e.g. 100000 = unchunked)")
    ap.add_argument("--stage", action="store_true", help="the whole face stage with the shipped model and settings")
    ap.add_argument("--filtering", action=argparse.BooleanOptionalAction, default=False,
                    help="--stage: with prediction filtering (default: off, as the pipeline's default)")
    args = ap.parse_args()
    for n in args.sizes:
        if args.stage:
            r = subprocess.run([sys.executable, "-c", STAGE, str(n), str(args.threads),
                                "1" if args.filtering else "0"], capture_output=True, text=True)
            print(r.stdout.strip() if r.returncode == 0 else f"N={n} failed: {r.stderr[-2000:]}", flush=True)
            continue
        r = subprocess.run([sys.executable, "-c", CHILD, str(n), str(args.threads), "1" if args.masked else "0",
                            str(args.pair_chunk)],
                           capture_output=True, text=True)
        print(r.stdout.strip() if r.returncode == 0 else f"N={n} failed: {r.stderr[-2000:]}", flush=True)


if __name__ == "__main__":
    main()
