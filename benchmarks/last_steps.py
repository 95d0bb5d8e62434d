"""The generated result's last touches, edge turns and edge splits (``faces.swap``, ``faces.refine``), set several
ways on results saved by an earlier run, scored as ``fastmesh eval`` scores them.

Usage: OMP_NUM_THREADS=1 nice python benchmarks/last_steps.py --saved DIR [--data data/eval-oop]
       [--variants turn,split1,turn+split1] [--json OUT]

``--saved``: the results of ``fastmesh eval --save DIR`` (the shipped code before the steps weighed here), each
``DIR/<input name>.ply`` beside ``data/{inputs,reference}/<input name>.*``.  A variant is a ``+``-joined list of
steps applied in order, in the input's unit cube, against its points with their normals turned outward:
``turn`` (edges turned, a turn that would cross a face undone; a pair that would fold never turns), ``turnfree``
(crossing turns kept), ``splitT`` (edges split at a tolerance of T cells, ``refine.refine``), ``splitTflat`` (the
same, flat regions split too).
Per result and variant: CD and HD (``evaluation.metrics.surface_distance``), the back-face share, silhouette IoU
and normal angle over 14 views fitted to the reference (``evaluation.seen``), faces crossing another face
(``faces.crossings``) and faces per reference face.  Unlike the pipeline, no step is weighed against the input.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from fastmesh.evaluation.metrics import surface_distance
from fastmesh.evaluation.seen import reference_sight, score_sight
from fastmesh.faces import refine as refine_module
from fastmesh.faces.crossings import crossing_faces
from fastmesh.faces.swap import swap_edges
from fastmesh.shapes.io import load_shape
from fastmesh.shapes.orientation import outward
from fastmesh.shapes.shape import Normalization
from fastmesh.tokenizer.grid import CELL


def _step(name: str, v: np.ndarray, f: np.ndarray, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """``f`` (or, for a split, (vertices, faces)) after the step ``name``."""
    if name in ("turn", "turnfree"):
        return v, swap_edges(v, f, points, normals, uncrossed=name == "turn")[0]
    flat = name.endswith("flat")
    cells = float(name.removeprefix("split").removesuffix("flat"))
    bend = refine_module.BEND_DEGREES
    refine_module.BEND_DEGREES = 0.0 if flat else bend
    try:
        v, f, _ = refine_module.refine(v, f, points, normals, cells * CELL)
    finally:
        refine_module.BEND_DEGREES = bend
    return v, f


def _row(mesh: tuple[np.ndarray, np.ndarray], ref, sight: tuple) -> dict:
    d = surface_distance(mesh, (ref.vertices, ref.faces))
    seen = score_sight(*mesh, *sight, len(ref.faces))
    return {"cd": d.cd, "hd": d.hd, "crossing_faces": int(crossing_faces(*mesh).sum()), "faces": int(len(mesh[1])),
            **{k: seen[k] for k in ("back_face_share", "silhouette_iou", "normal_angle", "faces_per_reference_face")}}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--saved", required=True)
    p.add_argument("--data", default="data/eval-oop")
    p.add_argument("--variants", default="turn,split1,turn+split1")
    p.add_argument("--json")
    args = p.parse_args()
    variants = args.variants.split(",")
    rows = []
    for path in sorted(Path(args.saved).glob("*.ply")):
        shape = load_shape(next(Path(args.data, "inputs").glob(path.stem + ".*")))
        ref = load_shape(next(Path(args.data, "reference").glob(path.stem + ".*")))
        saved = load_shape(path)
        norm = Normalization.fit(shape.vertices)
        points = norm.apply(shape.vertices)
        normals = outward(points, shape.normals)
        cams, views, _ = reference_sight(ref.vertices, ref.faces)
        row = {"name": path.stem, "saved": _row((saved.vertices, saved.faces), ref, (cams, views))}
        for variant in variants:
            v, f = norm.apply(saved.vertices), saved.faces
            for name in variant.split("+"):
                v, f = _step(name, v, f, points, normals)
            row[variant] = _row((norm.invert(v), f), ref, (cams, views))
        rows.append(row)
        print(path.stem, {k: round(r["normal_angle"], 2) for k, r in row.items() if k != "name"}, flush=True)
    keys = ["cd", "hd", "back_face_share", "silhouette_iou", "normal_angle", "faces_per_reference_face"]
    summary = {}
    for system in ["saved", *variants]:
        ratio = np.array([r[system]["faces_per_reference_face"] for r in rows])
        summary[system] = {**{k: round(float(np.mean([r[system][k] for r in rows])), 4) for k in keys},
                           "with_crossings": sum(r[system]["crossing_faces"] > 0 for r in rows),
                           "over_1_5x": int((ratio > 1.5).sum()),
                           "within_0_5_1_5x": int(((ratio >= 0.5) & (ratio <= 1.5)).sum())}
        print(system, summary[system])
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": rows, "summary": summary}, indent=1))


if __name__ == "__main__":
    main()
