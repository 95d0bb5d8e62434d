"""Each stage's time at 1 and N torch threads: the per-stage choice (``pipeline.STAGE_THREADS``: the vertex
decoder on one thread, the other stages on N) against N threads everywhere.

    python benchmarks/threads.py [--threads 1 2] [--rounds 1] [--weights DIR]

Inputs: the point clouds of ``benchmarks/decode_paths.py`` (an ellipsoid, a wavy sphere, a torus), generated at the
default settings.  Configurations run interleaved, input by input, so that a busy machine slows all alike.  Per
configuration the median over inputs and rounds of each stage's seconds (``GenerateResult.timings``) and of the
whole call.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from decode_paths import shapes  # noqa: E402

from fastmesh.models.onnx_decode import OrtDecoder  # noqa: E402
from fastmesh.params import GenerateParams  # noqa: E402
from fastmesh.pipeline import STAGES, Pipeline  # noqa: E402


def configurations(weights: str | None, counts: list[int]) -> dict:
    """name -> pipeline: per stage at each count, and N everywhere (the decoder too) for each count above 1."""
    out = {}
    for n in counts:
        out[f"{n} per stage"] = Pipeline.from_pretrained(weights, device="cpu", threads=n)
        if n > 1:
            pipe = Pipeline.from_pretrained(weights, device="cpu", threads=n)
            pipe.stage_threads = {}
            if isinstance(pipe.decoder, OrtDecoder):
                pipe.decoder = OrtDecoder(pipe.vertex, threads=n)
            out[f"{n} everywhere"] = pipe
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--weights", default=None)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--rounds", type=int, default=1)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    pipes = configurations(args.weights, args.threads)
    stages = [name for name, _, _ in STAGES] + ["total"]
    seen = {name: {s: [] for s in stages} for name in pipes}
    inputs = list(shapes().values())
    for _ in range(args.rounds):
        for shape in inputs:
            for name, pipe in pipes.items():
                torch.set_num_threads(pipe.threads)  # process-wide: each configuration sets its own
                t = time.perf_counter()
                result = pipe.generate(shape, GenerateParams(seed=0))
                seen[name]["total"].append(time.perf_counter() - t)
                for s, v in result.timings.items():
                    seen[name][s].append(v)
    table = {name: {s: round(statistics.median(v), 3) for s, v in per.items()} for name, per in seen.items()}
    if args.json:
        print(json.dumps(table))
        return 0
    print(f"{len(inputs)} inputs x {args.rounds} round(s), median seconds per generate")
    print(f"{'':16s}" + "".join(f"{s:>10s}" for s in stages))
    for name, row in table.items():
        print(f"{name:16s}" + "".join(f"{row[s]:10.2f}" for s in stages))
    return 0


if __name__ == "__main__":
    sys.exit(main())
