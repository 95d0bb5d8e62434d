"""Peak memory and time of one face-model pass (default FaceModelConfig) at N = 1000 / 2000 / 4000.

Each N runs in a fresh process so its peak resident set size (ru_maxrss) is its own.
Random weights and random distinct cells: memory and time do not depend on the values.

    python benchmarks/face_memory.py [--sizes 1000 2000 4000] [--threads 1] [--masked] [--pair-chunk K]

Prints one JSON line per N: baseline RSS after building the model, peak RSS during the
pass, seconds for the unmasked pass (and for a banded-mask pass with --masked).
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
torch.manual_seed(0)
model = FaceModel(FaceModelConfig(**({"pair_chunk": chunk} if chunk else {}))).eval()
rng = np.random.default_rng(0)
q = np.zeros((0, 3), dtype=np.int64)
while len(q) < n:
    q = np.unique(np.concatenate([q, rng.integers(0, 128, (n, 3))]), axis=0)
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 2000, 4000])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--masked", action="store_true", help="also time a pass with a band attention mask")
    ap.add_argument("--pair-chunk", type=int, default=0, help="override pair_chunk (e.g. 100000 = unchunked)")
    args = ap.parse_args()
    for n in args.sizes:
        r = subprocess.run([sys.executable, "-c", CHILD, str(n), str(args.threads), "1" if args.masked else "0",
                            str(args.pair_chunk)],
                           capture_output=True, text=True)
        print(r.stdout.strip() if r.returncode == 0 else f"N={n} failed: {r.stderr[-2000:]}", flush=True)


if __name__ == "__main__":
    main()
