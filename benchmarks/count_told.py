"""A ``target_faces`` told to the decoder (``SamplingConfig.read_count``, ``tell_below``) or held after it?

    python benchmarks/count_told.py --inputs data/eval-oop/inputs --reference data/eval-oop/reference \
        [--every 5] [--start 2] [--multiples 0.5 2 4] [--candidates 1] [--json OUT]
    python benchmarks/count_told.py --family 4 [--kinds sphere torus bumpy] [--json OUT]

Each input is generated at each target three ways, with the same seed: the default (the decoder is told the count
only far under the cells' expected vertices, ``tell_below``; else it makes its own count and the result is
brought to the target by ``facecount.hold_count``), never told (``tell_below`` 0) and always told
(``read_count``).  Folder mode: every ``--every``-th pair of an eval set (``fastmesh data eval-set``), targets at
``--multiples`` of its reference's faces (within ``params.TARGET_FACES``), scored against the reference.  Family
mode: ``--family`` point clouds of each curved kind of ``evaluation.primitives`` (turned, any units), a target
drawn log-uniformly in [100, 8000], scored against the shape sampled.  One row per run: CD / HD (% of the longest
side), faces and within +-20 %, watertight, pieces, seconds; then the means per way.
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

from fastmesh.evaluation.metrics import surface_distance  # noqa: E402
from fastmesh.evaluation.primitives import curved_input  # noqa: E402
from fastmesh.evaluation.quality import topology  # noqa: E402
from fastmesh.faces.facecount import TOLERANCE  # noqa: E402
from fastmesh.params import TARGET_FACES, GenerateParams, TunedParams  # noqa: E402
from fastmesh.pipeline import Pipeline  # noqa: E402
from fastmesh.shapes.io import load_shape  # noqa: E402

# The default (told only far under the cells' count, ``SamplingConfig.tell_below``), never told, always told.
WAYS = {"default": {}, "held": {"tell_below": 0.0}, "told": {"read_count": True}}


def runs(pipe: Pipeline, name: str, shape, truth, target: int, candidates: int) -> list[dict]:
    """Every way (``WAYS``) of one input at one target, scored against ``truth`` (vertices, faces)."""
    out = []
    for way, settings in WAYS.items():
        t = time.perf_counter()
        res = pipe.generate(shape, TunedParams(settings, GenerateParams(target_faces=target, candidates=candidates)))
        secs = time.perf_counter() - t
        d = surface_distance((res.vertices, res.faces), truth)
        q = topology(res.faces)
        out.append({"input": name, "target": target, "way": way, "cd": round(d.cd, 4), "hd": round(d.hd, 3),
                    "faces": int(len(res.faces)), "within": bool(abs(len(res.faces) - target) <= TOLERANCE * target),
                    "watertight": bool(q["watertight"]), "pieces": int(q["pieces"]), "seconds": round(secs, 2)})
        print(json.dumps(out[-1]), flush=True)
    return out


def folder(pipe: Pipeline, args) -> list[dict]:
    import trimesh

    names = sorted(Path(args.inputs).glob("*.npz"))[args.start::args.every]
    rows = []
    for path in names:
        ref = trimesh.load(Path(args.reference) / f"{path.stem}.ply", process=False)
        for m in args.multiples:
            target = int(np.clip(round(len(ref.faces) * m), *TARGET_FACES))
            rows += runs(pipe, path.stem, load_shape(path), (ref.vertices, ref.faces), target, args.candidates)
    return rows


def family(pipe: Pipeline, args) -> list[dict]:
    rows = []
    for i, kind in enumerate(args.kinds):
        rng = np.random.default_rng([args.seed, i])
        for _ in range(args.family):
            mesh, shape = curved_input(kind, "points", rng)
            target = int(np.exp(rng.uniform(np.log(100), np.log(8000))))
            rows += runs(pipe, kind, shape, (mesh.vertices, mesh.faces), target, args.candidates)
    return rows


def summary(rows: list[dict]) -> dict:
    """Per way: runs, mean CD / HD / seconds, within, watertight; and the runs where each other way is nearer (CD)
    than always told."""
    out = {}
    for way in WAYS:
        mine = [r for r in rows if r["way"] == way]
        out[way] = {"runs": len(mine), **{k: round(float(np.mean([r[k] for r in mine])), 4)
                                          for k in ("cd", "hd", "seconds", "within", "watertight")}}
    told = [r for r in rows if r["way"] == "told"]
    for way in ("default", "held"):
        mine = [r for r in rows if r["way"] == way]
        out[f"{way}_nearer_than_told"] = sum(a["cd"] < b["cd"] for a, b in zip(mine, told, strict=True))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--inputs", metavar="DIR")
    ap.add_argument("--reference", metavar="DIR")
    ap.add_argument("--every", type=int, default=5)
    ap.add_argument("--start", type=int, default=2)
    ap.add_argument("--multiples", type=float, nargs="+", default=[0.5, 2.0, 4.0])
    ap.add_argument("--family", type=int, default=0, metavar="N", help="family mode: N inputs of each kind")
    ap.add_argument("--kinds", nargs="+", default=["sphere", "torus", "bumpy"])
    ap.add_argument("--seed", type=int, default=7, help="of the family drawn")
    ap.add_argument("--candidates", type=int, default=1)
    ap.add_argument("--weights", default=None, metavar="DIR")
    ap.add_argument("--json", default=None, metavar="OUT")
    args = ap.parse_args()
    if not args.family and not (args.inputs and args.reference):
        ap.error("give --inputs and --reference, or --family N")
    torch.set_num_threads(1)
    pipe = Pipeline.from_pretrained(args.weights)
    rows = family(pipe, args) if args.family else folder(pipe, args)
    summ = summary(rows)
    print(json.dumps(summ, indent=2))
    if args.json:
        Path(args.json).write_text(json.dumps({"summary": summ, "rows": rows}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
