"""The vertex stage alone under other sampling settings: how each moves precision, recall and the count.

    python benchmarks/sampling_sweep.py --inputs DIR --reference DIR [--weights W] [--limit N] [--json]
        [--variants '{}' '{"cell_weight": 10}' '{"pace": 0.65}' ...]

Each variant is a JSON object of ``SamplingConfig`` fields that replace the defaults.  Per input the
decoder makes the default number of candidates as one batch, exactly as ``Pipeline.generate`` does,
and every candidate's vertices (cell centres, before the enhancer and the face stage) are scored with
``metrics.vertex_metrics`` against the reference's artist vertices; the summary averages over all
candidates.  ``fastmesh eval`` scores the returned mesh instead (the chosen candidate, the vertices
its faces use), so its figures run a little higher; use this to compare settings, that to report.

Per variant: mean P@1 / R@1 / P@2 / R@2, share on the surface, the count ratio's median and mean, the
share of counts within 0.7-1.4x, the correlation of log count with log reference count, candidates with
400 or more vertices, and seconds per input.
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

from fastmesh.batch import decode  # noqa: E402
from fastmesh.evaluation.eval import artist_vertices, pair_inputs  # noqa: E402
from fastmesh.evaluation.metrics import vertex_metrics  # noqa: E402
from fastmesh.params import GenerateParams, TunedParams  # noqa: E402
from fastmesh.pipeline import Pipeline  # noqa: E402
from fastmesh.request import Request  # noqa: E402
from fastmesh.shapes.io import load_shape  # noqa: E402
from fastmesh.tokenizer import dequantize  # noqa: E402

BIG = 400  # a candidate with this many vertices or more: a run towards the cap


def candidates(pipe: Pipeline, shape, params: GenerateParams) -> list[np.ndarray]:
    """(N_k, 3) vertices of each candidate in the shape's own frame: the pipeline's decoding (and its moves of
    the vertices by the cell evidence, ``snap_margin``), stopped there."""
    req = Request.start(shape, params)
    frame = pipe._frame(req, np.eye(3))
    steps = pipe._decode(req, [frame], lambda share: None)
    (seqs,) = decode(pipe.decoder, [next(steps)])
    out = []
    for seq in seqs:
        q = pipe.vertex_cells(seq.cpu().numpy(), frame.logodds, params)
        out.append(frame.norm.invert(dequantize(q)) if len(q) else np.zeros((0, 3)))
    return out


def summarise(rows: list[dict], seconds: float, n_inputs: int) -> dict:
    ratio = np.array([r["count_ratio"] for r in rows])
    gen = np.log([max(r["generated"], 1) for r in rows])
    ref = np.log([r["reference"] for r in rows])
    corr = float(np.corrcoef(gen, ref)[0, 1]) if len(rows) > 1 and gen.std() > 0 and ref.std() > 0 else float("nan")
    out = {k: round(float(np.mean([r[k] for r in rows])), 3)
           for k in ("precision_1", "recall_1", "precision_2", "recall_2")}
    if all("on_surface" in r for r in rows):
        out["on_surface"] = round(float(np.mean([r["on_surface"] for r in rows])), 3)
    out.update(count_ratio_median=round(float(np.median(ratio)), 2), count_ratio_mean=round(float(ratio.mean()), 2),
               within_0_7_1_4=round(float(((ratio >= 0.7) & (ratio <= 1.4)).mean()), 2),
               count_log_correlation=round(corr, 2), big=int(sum(r["generated"] >= BIG for r in rows)),
               seconds_per_input=round(seconds / max(n_inputs, 1), 2))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--inputs", required=True)
    ap.add_argument("--reference", required=True)
    ap.add_argument("--weights", default=None)
    ap.add_argument("--variants", nargs="+", default=["{}"], help="JSON objects of SamplingConfig fields")
    ap.add_argument("--limit", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", action="store_true", help="print every row as JSON too")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    variants = [json.loads(v) for v in args.variants]
    try:
        tuned = [TunedParams(v) for v in variants]
    except ValueError as e:
        ap.error(str(e))
    pipe = Pipeline.from_pretrained(args.weights)
    pairs = pair_inputs(args.inputs, args.reference)
    pairs = pairs[: args.limit] if args.limit else pairs
    report = {"weights": str(pipe.source), "inputs": len(pairs), "variants": []}
    for overrides, params in zip(variants, tuned, strict=True):
        rows, t = [], time.perf_counter()
        for inp, ref_path in pairs:
            shape, ref = load_shape(inp), load_shape(ref_path)
            artist = artist_vertices(ref, shape)
            for k, v in enumerate(candidates(pipe, shape, params)):
                row = vertex_metrics(artist["norm"].apply(v), artist["reference"], *artist["surface"])
                rows.append({"name": inp.stem, "candidate": k, **row})
        summary = summarise(rows, time.perf_counter() - t, len(pairs))
        print(json.dumps(overrides), json.dumps(summary), flush=True)
        report["variants"].append({"overrides": overrides, "summary": summary, **({"rows": rows} if args.json else {})})
    if args.json:
        print(json.dumps(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
