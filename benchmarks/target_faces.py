"""How well ``target_faces`` is followed: per target, the share of results within +-30 % of it.

    python benchmarks/target_faces.py --inputs DIR [--targets 100 300 1000 2000] [--limit N] [--weights DIR]

Runs the pipeline on every input once per target (default settings otherwise) and once without a target,
and prints per target the median face count, the share within +-30 % and the mean seconds.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fastmesh.io import SUPPORTED_FORMATS, load_shape  # noqa: E402
from fastmesh.params import GenerateParams  # noqa: E402
from fastmesh.pipeline import GenerationError, Pipeline  # noqa: E402

TOLERANCE = 0.3


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--inputs", required=True)
    ap.add_argument("--targets", type=int, nargs="+", default=[100, 300, 1000, 2000])
    ap.add_argument("--weights", default=None)
    ap.add_argument("--candidates", type=int, default=GenerateParams().candidates)
    ap.add_argument("--limit", type=int, default=0)
    args = ap.parse_args()
    torch.set_num_threads(1)
    files = sorted(f for f in Path(args.inputs).iterdir() if f.suffix.lower().lstrip(".") in SUPPORTED_FORMATS)
    files = files[: args.limit or None]
    pipe = Pipeline.from_pretrained(args.weights)
    out = {}
    for target in [None, *args.targets]:
        faces, secs, failed = [], [], 0
        for f in files:
            t = time.perf_counter()
            try:
                res = pipe.generate(load_shape(f), GenerateParams(candidates=args.candidates, target_faces=target))
            except GenerationError:
                failed += 1
                continue
            secs.append(time.perf_counter() - t)
            faces.append(len(res.faces))
        faces_a = np.array(faces)
        row = {"results": len(faces), "failed": failed, "median_faces": float(np.median(faces_a)) if len(faces) else 0,
               "mean_seconds": round(float(np.mean(secs)), 3) if secs else 0}
        if target is not None:
            row["within_30pct"] = round(float((np.abs(faces_a - target) <= TOLERANCE * target).mean()), 3)
        out["none" if target is None else str(target)] = row
        print(f"target {target}: {row}", file=sys.stderr, flush=True)
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
