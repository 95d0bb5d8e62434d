"""Vertex-stage ablation on an eval set: decoder with the cell evidence, a decoder without it, and the cell
evidence alone, side by side on the same inputs.

    python benchmarks/vertex_ablation.py --inputs DIR --reference DIR [--without DIR] [--limit N] [--json]

Systems (vertex metrics of ``fastmesh.evaluation.metrics.vertex_metrics``, in the reference's frame):

- ``decoder+cells``: the vertices of the pipeline's mesh with ``--weights`` (default: the shipped ones);
- ``decoder``: the same with ``--without``: a decoder that does not read the cell evidence (its folder, run with
  the other networks and settings of ``--weights``, or a whole weights folder; ``checkpoints/vertex-no-cells``
  is such a decoder, trained on the same corpus);
- ``cells@decoder``: the cell network alone, its best cells after one-cell suppression, as many as the
  decoder with cells generated;
- ``cells@own``: the same, as many as the cells' expected count (the sum of their probabilities);
- ``random@decoder``: as many random candidate cells (the no-learning floor).

Per system the summary also gives ``count_log_correlation``: how closely log(count) follows log(reference
count) over the meshes (a count that follows the shape, not a fixed length).

The decoders are scored on the vertices of the returned mesh (those its faces use: what a user gets); the
cells-alone systems take as many cells as the decoder generated before faces were built.
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

from fastmesh.evaluation.eval import pair_inputs  # noqa: E402
from fastmesh.evaluation.metrics import vertex_metrics  # noqa: E402
from fastmesh.models.cells import select_cells  # noqa: E402
from fastmesh.models.checkpoint import load_model  # noqa: E402
from fastmesh.params import GenerateParams  # noqa: E402
from fastmesh.pipeline import CELL_SEED, Pipeline  # noqa: E402
from fastmesh.shapes.io import load_shape, sample_surface
from fastmesh.shapes.shape import Normalization
from fastmesh.tokenizer import dequantize  # noqa: E402

KEYS = ("precision_1", "recall_1", "precision_2", "recall_2", "on_surface", "count_ratio")


def _log_correlation(rows: list[dict], system: str) -> float:
    """Correlation of log(count) with log(reference count) over the meshes: does the count follow the shape?
    (NaN when the counts do not vary.)"""
    gen = np.log([max(r[system]["generated"], 1) for r in rows])
    ref = np.log([r[system]["reference"] for r in rows])
    if len(rows) < 2 or gen.std() == 0 or ref.std() == 0:
        return float("nan")
    return round(float(np.corrcoef(gen, ref)[0, 1]), 3)


def _without(path: str, pipe: Pipeline) -> Pipeline:
    """``--without``: a whole weights folder, or a vertex decoder's folder put in place of ``pipe``'s decoder."""
    if (Path(path) / "vertex").is_dir():
        return Pipeline.from_pretrained(path)
    vertex, _ = load_model(path)
    if vertex.cfg.evidence_cells:
        raise SystemExit(f"{path}: this decoder reads the cell evidence; --without wants one that does not")
    return Pipeline(vertex, pipe.enhancer, pipe.face, device=pipe.device, filter_config=pipe.filter_config,
                    triangle_config=pipe.triangle_config, source=path, threads=pipe.threads, cell_net=pipe.cell_net,
                    fit_config=pipe.fit_config)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--inputs", required=True)
    ap.add_argument("--reference", required=True)
    ap.add_argument("--weights", default=None, help="pipeline whose decoder reads the cell evidence")
    ap.add_argument("--without", default=None,
                    help="pipeline whose decoder does not, or such a decoder alone (e.g. checkpoints/vertex-no-cells), "
                         "run with the other networks and settings of --weights (skipped if not given)")
    ap.add_argument("--candidates", type=int, default=GenerateParams().candidates)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--limit", type=int, default=0)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(1)
    pairs = pair_inputs(args.inputs, args.reference)[: args.limit or None]
    pipe = Pipeline.from_pretrained(args.weights)
    if pipe.cell_net is None:
        raise SystemExit(f"{pipe.source} has no cell evidence network")
    other = _without(args.without, pipe) if args.without else None
    params = GenerateParams(seed=args.seed, candidates=args.candidates)
    rng = np.random.default_rng(args.seed)
    rows = []
    for inp, ref_path in pairs:
        ref, shape = load_shape(ref_path), load_shape(inp)
        ref_norm = Normalization.fit(ref.vertices)
        in_norm = Normalization.fit(shape.vertices)
        ref_unit = ref_norm.apply(ref.vertices)

        def score(vertices_input_frame, ref_norm=ref_norm, ref_unit=ref_unit, faces=ref.faces):
            return vertex_metrics(ref_norm.apply(vertices_input_frame), ref_unit, ref_unit, faces)

        row = {"name": inp.stem}
        t = time.perf_counter()
        res = pipe.generate(shape, params)
        row["seconds"] = round(time.perf_counter() - t, 3)
        row["decoder+cells"] = score(res.vertices)
        n_dec = int(res.info["generated_vertices"])
        if other is not None:
            row["decoder"] = score(other.generate(shape, params).vertices)
        unit = in_norm.apply(shape.vertices)
        pts, nrm = sample_surface(shape, pipe.cell_net.cfg.n_points, seed=CELL_SEED, vertices=unit)
        cells, logits = pipe.cell_net.score(pts, nrm)
        own = max(3, int(round(float(torch.sigmoid(logits).sum()))))
        for name, chosen in (("cells@decoder", select_cells(cells, logits, count=n_dec)),
                             ("cells@own", select_cells(cells, logits, count=own)),
                             ("random@decoder", cells.numpy()[rng.choice(len(cells), min(n_dec, len(cells)),
                                                                         replace=False)])):
            row[name] = score(in_norm.invert(dequantize(chosen)))
        rows.append(row)
        print(f"{inp.stem[:60]}: " + "  ".join(f"{k} P1 {row[k]['precision_1']:.2f} R1 {row[k]['recall_1']:.2f}"
                                               for k in row if isinstance(row[k], dict)), file=sys.stderr, flush=True)
    systems = [k for k in rows[0] if isinstance(rows[0][k], dict)]
    summary = {s: {**{k: round(float(np.mean([r[s][k] for r in rows])), 4) for k in KEYS},
                   "median_count_ratio": round(float(np.median([r[s]["count_ratio"] for r in rows])), 3),
                   "count_log_correlation": _log_correlation(rows, s)}
               for s in systems}
    summary["meshes"] = len(rows)
    summary["mean_seconds"] = round(float(np.mean([r["seconds"] for r in rows])), 3)
    print(json.dumps({"summary": summary, "meshes": rows} if args.json else summary, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
