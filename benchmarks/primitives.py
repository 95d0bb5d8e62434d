"""The ladder of simple shapes: does the pipeline find a primitive's own vertices?

    python benchmarks/primitives.py [--weights DIR] [--shapes box,cone] [--seed 0] [--threads N] [--json]

Each shape of ``fastmesh.evaluation.primitives.LADDER`` (box, L-shaped block, box with a square through-hole,
cylinder and cone of 16 sides, icosphere of 1 and 2 subdivisions, torus) is sampled to 8,192
points with normals, and the pipeline (default settings) makes a mesh from that point cloud.
Per shape: the primitive's vertex count, the generated count and their ratio, precision and
recall within one 7-bit cell of the primitive's vertices, the share of generated vertices within
1.5 cells of its surface (``fastmesh.evaluation.metrics.vertex_metrics``, in the primitive's normalised
frame), and the seconds of ``generate``.  ``ok`` marks the target: recall within one
cell >= 0.9 and at most 1.5x the primitive's vertices.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fastmesh.evaluation.metrics import vertex_metrics  # noqa: E402
from fastmesh.evaluation.primitives import LADDER, point_cloud, primitive  # noqa: E402
from fastmesh.params import GenerateParams  # noqa: E402
from fastmesh.pipeline import GenerationError, Pipeline  # noqa: E402
from fastmesh.shapes.shape import Normalization

TARGET_RECALL = 0.9
TARGET_COUNT = 1.5


def run_shape(pipe: Pipeline, name: str, params: GenerateParams) -> dict:
    mesh = primitive(name)
    cloud = point_cloud(mesh, seed=params.seed)
    norm = Normalization.fit(mesh.vertices)
    t = time.perf_counter()
    try:
        res = pipe.generate(cloud, params)
    except GenerationError as e:
        return {"shape": name, "reference": len(mesh.vertices), "failed": e.code,
                "seconds": round(time.perf_counter() - t, 3)}
    seconds = time.perf_counter() - t
    vm = vertex_metrics(norm.apply(res.vertices), norm.apply(mesh.vertices), norm.apply(mesh.vertices), mesh.faces)
    ok = vm["recall_1"] >= TARGET_RECALL and vm["count_ratio"] <= TARGET_COUNT
    return {"shape": name, **vm, "faces": int(len(res.faces)), "seconds": round(seconds, 3), "ok": ok}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--weights", default=None, metavar="DIR", help="weights folder (default: the shipped ones)")
    ap.add_argument("--shapes", default=",".join(LADDER), help="comma-separated subset of the ladder")
    ap.add_argument("--seed", type=int, default=0, help="seed of the point sample and of generation")
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: the pipeline's)")
    ap.add_argument("--json", action="store_true", help="print the rows as JSON")
    args = ap.parse_args()
    pipe = Pipeline.from_pretrained(args.weights, threads=args.threads)
    params = GenerateParams(seed=args.seed)
    rows = [run_shape(pipe, name, params) for name in args.shapes.split(",")]
    if args.json:
        print(json.dumps({"weights": pipe.source, "rows": rows}, indent=2))
        return 0
    print(f"weights {pipe.source}, default settings ({params.candidates} candidates), seed {args.seed}, "
          f"{torch.get_num_threads()} thread(s)")
    print(f"{'shape':<11} {'ref V':>5} {'gen V':>5} {'ratio':>5} {'P@1':>5} {'R@1':>5} {'on-surf':>7} {'s':>6}  ok")
    for r in rows:
        if "failed" in r:
            print(f"{r['shape']:<11} {r['reference']:>5} failed: {r['failed']} ({r['seconds']:.1f} s)")
            continue
        print(f"{r['shape']:<11} {r['reference']:>5} {r['generated']:>5} {r['count_ratio']:>5.2f} "
              f"{r['precision_1']:>5.2f} {r['recall_1']:>5.2f} {r['on_surface']:>7.2f} {r['seconds']:>6.1f}  "
              f"{'yes' if r['ok'] else 'no'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
