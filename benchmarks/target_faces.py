"""Does ``target_faces`` hold?  The share of results within +-20 % of it, per input kind.

    python benchmarks/target_faces.py [--n 9] [--stage hold|pipeline] [--seed 0] [--weights DIR]
                                      [--candidates K] [--max-vertices N] [--json OUT]
    python benchmarks/target_faces.py --inputs DIR [--targets 100 300 1000 2000] [--limit N] [--weights DIR]

Family mode (the first form): ``--n`` inputs of every kind of ``fastmesh.evaluation.primitives.curved_input`` (sphere,
torus, box, bumpy sphere; turned, in metres or millimetres, 10^-2 to 10^2 across) given as meshes and as
points, each with a target drawn log-uniformly in [100, 8000].  ``--stage pipeline`` runs the whole pipeline
(the shipped weights unless ``--weights``); ``--stage hold`` gives ``facecount.hold_count`` a stand-in result
of 40 to 2,000 faces (``primitives.coarse_copy``: the count step alone, in seconds).  Prints one row per input
(kind, input, target, the faces before the count step, achieved, within, closed before and after) and the
share within per kind and input; ``--json`` writes them.

Folder mode (the second form): every shape in DIR once per target, the median faces and the share within.
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

from fastmesh.evaluation.primitives import CURVED_KINDS, coarse_copy, curved_input  # noqa: E402
from fastmesh.evaluation.quality import topology  # noqa: E402
from fastmesh.faces.facecount import TOLERANCE, hold_count, input_samples  # noqa: E402
from fastmesh.params import GenerateParams  # noqa: E402
from fastmesh.pipeline import GenerationError, Pipeline  # noqa: E402
from fastmesh.shapes.io import load_shape
from fastmesh.shapes.shape import SUPPORTED_FORMATS

GIVEN = ("mesh", "points")
TARGETS = (100, 8000)


def _within(faces: int, target: int) -> bool:
    return abs(faces - target) <= TOLERANCE * target


def family_row(kind: str, given: str, rng: np.random.Generator, pipe: Pipeline | None, params: dict) -> dict:
    """One input of ``kind`` given as ``given``, its target, and what the count step (``pipe`` None) or the
    pipeline made of it."""
    mesh, shape = curved_input(kind, given, rng)
    target = int(np.exp(rng.uniform(*np.log(TARGETS))))
    row = {"kind": kind, "input": given, "target": target}
    t = time.perf_counter()
    if pipe is None:
        v, f = coarse_copy(mesh, int(np.exp(rng.uniform(np.log(40), np.log(2000)))), rng)
        row["before"], closed_before = int(len(f)), topology(f)["watertight"]
        v, f, step = hold_count(v, f, target, *input_samples(shape))
    else:
        try:
            res = pipe.generate(shape, GenerateParams(target_faces=target, **params))
        except GenerationError as e:
            return {**row, "failed": e.code}
        v, f, step = res.vertices, res.faces, res.quality["count_step"]
        closed_before = None
        row["before"] = res.info["faces_before_count"]
    q = topology(f)
    return {**row, "achieved": int(len(f)), "within": _within(len(f), target), "step": step,
            "closed_before": closed_before, "closed": q["watertight"], "seconds": round(time.perf_counter() - t, 3)}


def summary(rows: list[dict]) -> list[dict]:
    """Per kind and input: results, failures and the share within +-20 % (failures count as misses)."""
    out = []
    for kind in dict.fromkeys(r["kind"] for r in rows):
        for given in dict.fromkeys(r["input"] for r in rows):
            mine = [r for r in rows if r["kind"] == kind and r["input"] == given]
            if mine:
                out.append({"kind": kind, "input": given, "n": len(mine),
                            "failed": sum("failed" in r for r in mine),
                            "within": round(sum(r.get("within", False) for r in mine) / len(mine), 3)})
    return out


def print_family(rows: list[dict], summ: list[dict]) -> None:
    print(f"{'kind':8s} {'input':7s} {'target':>6s} {'before':>6s} {'achieved':>8s} {'within':>6s} "
          f"{'step':>10s} {'closed':>13s} {'s':>6s}")
    for r in rows:
        if "failed" in r:
            print(f"{r['kind']:8s} {r['input']:7s} {r['target']:6d} failed: {r['failed']}")
            continue
        closed = f"{r['closed_before']} -> {r['closed']}" if r["closed_before"] is not None else str(r["closed"])
        print(f"{r['kind']:8s} {r['input']:7s} {r['target']:6d} {r['before']:6d} {r['achieved']:8d} "
              f"{'yes' if r['within'] else 'NO':>6s} {r['step']:>10s} {closed:>13s} {r['seconds']:6.2f}")
    print()
    for s in summ:
        print(f"{s['kind']:8s} {s['input']:7s} within +-20 %: {s['within']:.0%} of {s['n']}"
              + (f" ({s['failed']} failed)" if s["failed"] else ""))
    total = sum(r.get("within", False) for r in rows)
    print(f"all: {total}/{len(rows)} within +-20 %")


def family(args) -> dict:
    pipe = Pipeline.from_pretrained(args.weights) if args.stage == "pipeline" else None
    params = {k: v for k, v in (("candidates", args.candidates), ("max_vertices", args.max_vertices))
              if v is not None}
    rows = []
    for i, kind in enumerate(CURVED_KINDS):
        for j, given in enumerate(GIVEN):
            rng = np.random.default_rng([args.seed, i, j])
            for _ in range(args.n):
                rows.append(family_row(kind, given, rng, pipe, params))
                print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    summ = summary(rows)
    print_family(rows, summ)
    return {"stage": args.stage, "seed": args.seed, "params": params, "summary": summ, "rows": rows}


def folder(args) -> dict:
    files = sorted(f for f in Path(args.inputs).iterdir() if f.suffix.lower().lstrip(".") in SUPPORTED_FORMATS)
    files = files[: args.limit or None]
    pipe = Pipeline.from_pretrained(args.weights)
    out = {}
    for target in [None, *args.targets]:
        faces, secs, failed = [], [], 0
        for f in files:
            t = time.perf_counter()
            try:
                res = pipe.generate(load_shape(f), GenerateParams(target_faces=target))
            except GenerationError:
                failed += 1
                continue
            secs.append(time.perf_counter() - t)
            faces.append(len(res.faces))
        row = {"results": len(faces), "failed": failed, "median_faces": float(np.median(faces)) if faces else 0,
               "mean_seconds": round(float(np.mean(secs)), 3) if secs else 0}
        if target is not None:
            row["within_20pct"] = round(float(np.mean([_within(n, target) for n in faces])), 3) if faces else 0
        out["none" if target is None else str(target)] = row
        print(f"target {target}: {row}", flush=True)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=9, help="inputs of each kind, as meshes and as points each")
    ap.add_argument("--stage", choices=("hold", "pipeline"), default="pipeline")
    ap.add_argument("--seed", type=int, default=0, help="of the family drawn")
    ap.add_argument("--inputs", default=None, metavar="DIR", help="folder mode: these shapes instead")
    ap.add_argument("--targets", type=int, nargs="+", default=[100, 300, 1000, 2000], help="folder mode")
    ap.add_argument("--limit", type=int, default=0, help="folder mode: the first N shapes")
    ap.add_argument("--weights", default=None, metavar="DIR")
    ap.add_argument("--candidates", type=int, default=None)
    ap.add_argument("--max-vertices", type=int, default=None)
    ap.add_argument("--json", default=None, metavar="OUT", help="write the rows and summary here")
    args = ap.parse_args()
    torch.set_num_threads(1)
    out = folder(args) if args.inputs else family(args)
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
