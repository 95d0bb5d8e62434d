"""The vertex decoding paths on the same inputs: the eager loop (``models.generate``, with the eager torch step or
ONNX Runtime's) against the static-shape loop (``models.decode``), run eagerly and, on CUDA, captured as a graph.

    python benchmarks/decode_paths.py [--device cpu|cuda] [--rounds 3] [--threads 1] [--json]

Inputs: point clouds of a random ellipsoid, wavy sphere and torus (``tests/gpu_inputs.py``: smooth surfaces, which
the pipeline decodes rather than rebuilds from planes), each encoded as the pipeline encodes it (cell grid,
prefixes and evidence of the default two candidates).  Every path decodes each input at the default sampling
settings, the paths interleaved over ``--rounds`` rounds so that a busy machine slows all alike; each path's
first call (ONNX export, graph capture) is a warm-up, not timed.

Per path: the median seconds of a decoding and its steps per second (the loop's steps: each advances every row
by one token), over all inputs.  The pipeline's default on a device is the fastest path here
(``onnx_decode.choose_decoder``).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from gpu_inputs import smooth_cloud, turned  # noqa: E402

from fastmesh.models.decode import StaticDecoder  # noqa: E402
from fastmesh.models.generate import StackedEvidence, generate  # noqa: E402
from fastmesh.params import GenerateParams  # noqa: E402
from fastmesh.pipeline import Pipeline  # noqa: E402
from fastmesh.request import Frame  # noqa: E402


def shapes(seed: int = 0) -> dict:
    """Named point clouds whose vertices the pipeline decodes (smooth surfaces: no rebuild from planes), turned."""
    rng = np.random.default_rng(seed)
    return {kind: turned(smooth_cloud(kind, seed + i), rng) for i, kind in enumerate(("ellipsoid", "wavy", "torus"))}


def encoded(pipe: Pipeline, shape, params: GenerateParams) -> tuple[torch.Tensor, StackedEvidence | None]:
    """The decoder's inputs for ``shape`` as ``Pipeline._decode`` makes them: (C, M, dim) prefixes and the
    evidence of the C candidates."""
    frame = Frame.of(shape)
    cells = pipe._logodds(frame)
    encs = [pipe._encode(frame, params.seed + k, params, cells) for k in range(params.candidates)]
    evidence = [e[3] for e in encs]
    return torch.cat([e[2] for e in encs]), None if evidence[0] is None else StackedEvidence(evidence)


def paths(pipe: Pipeline) -> dict:
    """The decoders to compare on the pipeline's device."""
    out = {"torch": pipe.vertex}
    if pipe.device.type == "cpu":
        from fastmesh.models.onnx_decode import OrtDecoder

        out["onnx"] = OrtDecoder(pipe.vertex)
        out["static"] = StaticDecoder(pipe.vertex)
    else:
        out["static"] = StaticDecoder(pipe.vertex, capture=False, compiled=False)
        if pipe.device.type == "cuda":
            out["static_graph"] = StaticDecoder(pipe.vertex, capture=True, compiled=False)
            out["static_graph_fused"] = StaticDecoder(pipe.vertex, capture=True, compiled=True)
    return out


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def measure(pipe: Pipeline, decoders: dict, inputs: list, cfg, rounds: int) -> dict:
    """Per decoder: {"s": median seconds per decoding, "steps_per_s": loop steps over seconds, all inputs}."""
    for dec in decoders.values():  # warm-up: exports, captures, first-call allocations
        generate(dec, *inputs[0][:1], cfg, evidence=inputs[0][1])
    times = {name: [] for name in decoders}
    steps = {name: 0 for name in decoders}
    for _ in range(rounds):
        for prefix, evidence in inputs:
            for name, dec in decoders.items():
                sync(pipe.device)
                t = time.perf_counter()
                seqs = generate(dec, prefix, cfg, evidence=evidence)
                sync(pipe.device)
                times[name].append(time.perf_counter() - t)
                steps[name] += max(len(s) for s in seqs) - 1
    return {name: {"s": round(statistics.median(times[name]), 4),
                   "steps_per_s": round(steps[name] / sum(times[name]), 1)} for name in decoders}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--weights", default=None)
    ap.add_argument("--device", default=None, help="cpu or cuda (default: cuda when there is one)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--json", action="store_true", help="one JSON line, no table")
    args = ap.parse_args()
    pipe = Pipeline.from_pretrained(args.weights, device=args.device, threads=args.threads)
    params = GenerateParams(seed=0)
    cfg = params.sampling(pipe.max_vertices)
    inputs = [encoded(pipe, s, params) for s in shapes().values()]
    result = {"device": str(pipe.device), "threads": torch.get_num_threads(), "candidates": params.candidates,
              "paths": measure(pipe, paths(pipe), inputs, cfg, args.rounds)}
    if args.json:
        print(json.dumps(result))
        return 0
    print(f"device {result['device']}, {result['threads']} thread(s), {params.candidates} candidates a decoding, "
          f"{len(inputs)} inputs x {args.rounds} rounds")
    for name, r in result["paths"].items():
        print(f"  {name:13s} {r['s']:8.3f} s/decoding  {r['steps_per_s']:8.1f} steps/s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
