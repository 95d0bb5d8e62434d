"""Simple shapes drawn at random: does the pipeline give them back exactly, closed or open as they are, whatever
their pose?

    python benchmarks/random_shapes.py [--n 10] [--kinds box,l_block,prism,cylinder,cone,tray,roof]
                                       [--inputs mesh,points,points_signs,points_bare] [--pose turned|axes|mm]
                                       [--seed 0] [--weights DIR]
                                       [--json]
    python benchmarks/random_shapes.py --kinds capsule,tube,torus,ellipsoid ...

Each shape of ``fastmesh.evaluation.primitives.random_shape`` (proportions and outlines at random) is posed
(``turned``: a random rotation; ``axes``: as built; ``mm``: turned, in millimetres up to 10 m from the origin)
and given to the pipeline (default settings) as its mesh or as 8,192 points with normals (``points``; with
normals of random sign, ``points_signs``; without normals, estimated as the service does, ``points_bare``).
Per shape:
``exact`` (as many vertices as the shape and each within one 7-bit cell of one of its own), ``closed``
(watertight), ``as_shape`` (edge-manifold with as many open edges as the shape: none for a closed one), the
pieces, CD/HD against the shape (% of its longest side), the frame the pipeline kept
(``turned_degrees``) and seconds.  The summary gives the shares per kind and input.  The round kinds (dense
curved meshes: capsules, tubes, tori, ellipsoids) have no artist vertices: for them ``closed`` and the pieces
are what counts.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fastmesh.evaluation.metrics import vertex_metrics  # noqa: E402
from fastmesh.evaluation.primitives import (  # noqa: E402
    OPEN_KINDS,
    RANDOM_KINDS,
    ROUND_KINDS,
    point_cloud,
    posed,
    random_shape,
)
from fastmesh.evaluation.quality import topology  # noqa: E402
from fastmesh.params import GenerateParams  # noqa: E402
from fastmesh.pipeline import GenerationError, Pipeline  # noqa: E402
from fastmesh.shapes.io import with_normals  # noqa: E402
from fastmesh.shapes.shape import Normalization, Shape  # noqa: E402


def run_one(pipe: Pipeline, kind: str, rng: np.random.Generator, given: str, pose: str) -> dict:
    mesh = posed(random_shape(kind, rng), rng, turn=pose != "axes", millimetres=pose == "mm")
    cloud_seed = 0 if given == "mesh" else int(rng.integers(1 << 16))  # the same shapes for each input
    shape = mesh if given == "mesh" else point_cloud(mesh, seed=cloud_seed)
    if given == "points_signs":  # as a scanner's or PCA's normals point
        signs = np.random.default_rng([cloud_seed, 1]).choice([-1.0, 1.0], (len(shape.vertices), 1))
        shape = Shape(vertices=shape.vertices, normals=shape.normals * signs)
    elif given == "points_bare":  # no normals: estimated as the service does (``io.with_normals``)
        shape = with_normals(Shape(vertices=shape.vertices))
    norm = Normalization.fit(mesh.vertices)
    t = time.perf_counter()
    try:
        res = pipe.generate(shape, GenerateParams())
    except GenerationError as e:
        return {"kind": kind, "input": given, "failed": e.code}
    vm = vertex_metrics(norm.apply(res.vertices), norm.apply(mesh.vertices), norm.apply(mesh.vertices), mesh.faces)
    q = res.quality
    open_edges = topology(mesh.faces)["boundary_edges"]
    return {"kind": kind, "input": given, "vertices": len(res.vertices), "reference": len(mesh.vertices),
            "exact": bool(len(res.vertices) == len(mesh.vertices) and vm["precision_1"] == 1.0),
            "closed": q["watertight"], "as_shape": q["boundary_edges"] == open_edges and q["non_manifold_edges"] == 0,
            "pieces": q["pieces"], "cd": q["cd"], "hd": q["hd"],
            "turned_degrees": res.info["turned_degrees"], "seconds": round(time.perf_counter() - t, 3)}


def summary(rows: list[dict]) -> list[dict]:
    out = []
    for kind in dict.fromkeys(r["kind"] for r in rows):
        for given in dict.fromkeys(r["input"] for r in rows):
            mine = [r for r in rows if r["kind"] == kind and r["input"] == given]
            ok = [r for r in mine if not r.get("failed")]
            out.append({"kind": kind, "input": given, "n": len(mine), "failed": len(mine) - len(ok),
                        "exact": sum(r["exact"] for r in ok) / len(mine),
                        "closed": sum(r["closed"] for r in ok) / len(mine),
                        "one_piece": sum(r["pieces"] == 1 for r in ok) / len(mine),
                        "as_shape": sum(r["as_shape"] for r in ok) / len(mine),
                        "exact_and_as_shape": sum(r["exact"] and r["as_shape"] for r in ok) / len(mine),
                        "mean_cd": float(np.mean([r["cd"] for r in ok])) if ok else None,
                        "mean_hd": float(np.mean([r["hd"] for r in ok])) if ok else None,
                        "mean_seconds": float(np.mean([r["seconds"] for r in ok])) if ok else None})
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=10, help="shapes of each kind")
    ap.add_argument("--kinds", default=",".join(RANDOM_KINDS + OPEN_KINDS))
    ap.add_argument("--inputs", default="mesh,points",
                    help="give each shape as its mesh, its points, points_signs, points_bare (comma-separated)")
    ap.add_argument("--pose", choices=("turned", "axes", "mm"), default="turned")
    ap.add_argument("--seed", type=int, default=0, help="of the family drawn")
    ap.add_argument("--weights", default=None, metavar="DIR")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--json", action="store_true", help="print every row as JSON too")
    args = ap.parse_args()
    pipe = Pipeline.from_pretrained(args.weights, threads=args.threads)
    rows = []
    for kind in args.kinds.split(","):
        for given in args.inputs.split(","):
            # the same shapes for each input
            rng = np.random.default_rng([args.seed, (RANDOM_KINDS + OPEN_KINDS + ROUND_KINDS).index(kind)])
            for _ in range(args.n):
                rows.append(run_one(pipe, kind, rng, given, args.pose))
                print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    table = summary(rows)
    print(f"{'kind':10} {'input':7} {'n':>3} {'exact':>6} {'closed':>7} {'as shape':>9} {'1 piece':>8} {'exact+as':>9} "
          f"{'CD':>6} {'HD':>6} {'s':>5}")
    for r in table:
        print(f"{r['kind']:10} {r['input']:7} {r['n']:3d} {r['exact']:6.2f} {r['closed']:7.2f} {r['as_shape']:9.2f} "
              f"{r['one_piece']:8.2f} {r['exact_and_as_shape']:9.2f} {r['mean_cd'] or 0:6.2f} {r['mean_hd'] or 0:6.2f} "
              f"{r['mean_seconds'] or 0:5.1f}")
    if args.json:
        print(json.dumps({"pose": args.pose, "seed": args.seed, "rows": rows, "summary": table}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
