"""Seconds of ``Pipeline.generate`` per input, for this tree's code or another checkout's.

    python benchmarks/generate_time.py --inputs data/eval-oop/inputs [--every 6] [--root DIR] [--threads 1]

Loads the pipeline once (the shipped weights of the code it runs), makes one warm-up result, then times
``generate`` with default settings on every ``--every``-th input and prints one JSON line: the median and mean
seconds and each input's.  ``--root`` runs another checkout's ``fastmesh`` (e.g. a ``git worktree`` of an
earlier commit) to compare two versions on the same machine: alternate the runs, the machine's load drifts.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--inputs", required=True, metavar="DIR", help="point clouds or meshes")
    ap.add_argument("--every", type=int, default=6, help="time every N-th input (sorted by name)")
    ap.add_argument("--root", default=str(Path(__file__).resolve().parents[1]), metavar="DIR",
                    help="the checkout whose fastmesh runs (default: this one)")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    sys.path.insert(0, args.root)
    import numpy as np

    from fastmesh.params import GenerateParams
    from fastmesh.pipeline import Pipeline
    from fastmesh.shapes.io import load_shape
    from fastmesh.shapes.shape import SUPPORTED_FORMATS

    files = sorted(f for f in Path(args.inputs).iterdir() if f.suffix.lower().lstrip(".") in SUPPORTED_FORMATS)
    files = files[:: max(1, args.every)]
    pipe = Pipeline.from_pretrained(threads=args.threads)
    pipe.generate(load_shape(files[0]), GenerateParams())  # warm-up: first-call costs are not the pipeline's
    runs = {}
    for f in files:
        shape = load_shape(f)
        t = time.perf_counter()
        pipe.generate(shape, GenerateParams())
        runs[f.name] = round(time.perf_counter() - t, 3)
    seconds = list(runs.values())
    print(json.dumps({"root": args.root, "median": float(np.median(seconds)), "mean": float(np.mean(seconds)),
                      "runs": runs}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
