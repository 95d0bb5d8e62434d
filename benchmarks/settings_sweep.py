"""Choose the shipped generation settings end to end: temperature x filtering x clean-up.

    python benchmarks/settings_sweep.py [--weights DIR] [--inputs data/eval-val30/inputs]
        [--reference data/eval-val30/reference] [--temperatures 0.3,0.2] [--variants c0.5,0.8-0.5,nofilt0.5]

For each temperature the vertices of every input are generated once (the pipeline as shipped);
then every face-stage variant runs on those same vertices, with and without dropping the longer
diagonal of flat 4-cliques, and is scored as ../shared/EVAL.md (CD/HD in % of the longest side),
plus both halves of CD (result -> reference: stray surface; reference -> result: holes) and faces.

Variants: ``cT`` constant threshold T in every filtering pass, ``A-B`` first/final thresholds,
``nofiltT`` one unfiltered pass at threshold T.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import fastmesh.pipeline as pipeline_module  # noqa: E402
import fastmesh.pipeline.candidate as candidate_module  # noqa: E402
from fastmesh.evaluation.eval import pair_inputs  # noqa: E402
from fastmesh.evaluation.metrics import surface_distance  # noqa: E402
from fastmesh.faces.filtering import FilterConfig, edges_from_logits, filter_predictions  # noqa: E402
from fastmesh.params import GenerateParams  # noqa: E402
from fastmesh.shapes.io import load_shape
from fastmesh.shapes.shape import Normalization


def variant(name: str) -> FilterConfig | float:
    if name.startswith("nofilt"):
        return float(name[6:])
    if name.startswith("c"):
        t = float(name[1:])
        return FilterConfig(first_threshold=t, final_threshold=t)
    first, final = name.split("-")
    return FilterConfig(first_threshold=float(first), final_threshold=float(final))


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--weights", default=None)
    ap.add_argument("--inputs", default="data/eval-val30/inputs")
    ap.add_argument("--reference", default="data/eval-val30/reference")
    ap.add_argument("--temperatures", default="0.3")
    ap.add_argument("--variants", default="c0.5,0.8-0.5")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    pipe = pipeline_module.Pipeline.from_pretrained(args.weights)
    pairs = pair_inputs(args.inputs, args.reference)
    names = args.variants.split(",")

    # Capture what the pipeline hands to its face stage, so each variant reuses the same vertices.
    seen: dict = {}
    run_edges, build_mesh = candidate_module.predict_edges, candidate_module.mesh_from_adjacency

    def spy_edges(predict, n, cfg, filtering=True):
        seen["predict"], seen["n"] = predict, n
        return run_edges(predict, n, cfg, filtering)

    def spy_mesh(positions, edges, cfg=None, points=None, logits=None):
        seen["positions"], seen["points"], seen["logits"] = positions, points, logits
        return build_mesh(positions, edges, cfg, points=points, logits=logits)

    candidate_module.predict_edges, candidate_module.mesh_from_adjacency = spy_edges, spy_mesh
    for temp in [float(t) for t in args.temperatures.split(",")]:
        rows: dict[tuple[str, bool], list] = {(k, d): [] for k in names for d in (False, True)}
        n_vert, t_vert = [], []
        for inp, ref_path in pairs:
            shape, ref = load_shape(inp), load_shape(ref_path)
            # One candidate: the spies must see the mesh that is scored (filtering on: they see it).
            out = pipe.generate(shape, GenerateParams(temperature=temp, candidates=1))
            n_vert.append(seen["n"])
            t_vert.append(out.timings["vertices"])
            norm = Normalization.fit(shape.vertices)
            for k in names:
                cfg = variant(k)
                if isinstance(cfg, float):
                    edges = edges_from_logits(seen["predict"](np.arange(seen["n"]), None), cfg)
                else:
                    edges = filter_predictions(seen["predict"], seen["n"], cfg).edges
                for diag in (False, True):
                    cfg_triangles = replace(pipe.triangle_config, drop_coplanar_diagonals=diag)  # the rest as shipped
                    v, f = build_mesh(seen["positions"], edges, cfg_triangles, points=seen["points"],
                                      logits=seen["logits"])
                    if len(f) == 0:
                        rows[k, diag].append([np.nan] * 6)
                        continue
                    d = surface_distance((norm.invert(v), f), (ref.vertices, ref.faces))
                    rows[k, diag].append([d.cd, d.hd, d.mean_ab, d.mean_ba, len(f), len(f) / len(ref.faces)])
        print(f"T={temp} mean generated vertices {np.mean(n_vert):.0f}, vertex stage {np.mean(t_vert):.2f} s",
              flush=True)
        for (k, diag), r in rows.items():
            a = np.array(r, dtype=float)
            print(f"  {k:10s} diag={int(diag)} CD {np.nanmean(a[:, 0]):.2f} HD {np.nanmean(a[:, 1]):.2f} "
                  f"gen->ref {np.nanmean(a[:, 2]):.2f} ref->gen {np.nanmean(a[:, 3]):.2f} F {np.nanmean(a[:, 4]):.0f} "
                  f"ratio {np.nanmean(a[:, 5]):.2f} fails {int(np.isnan(a[:, 0]).sum())}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
