"""Collapses of saved results to a tolerance, scored as ``fastmesh eval`` scores them: what fewer faces cost.

Reads the results ``fastmesh eval --save DIR`` wrote (``DIR/<name>.ply``, in the input's frame) and the eval set's
inputs and references, and collapses every result in the unit cube of its own vertices, each setting from the saved
result alone (no weighing, no rounds around folds, nothing kept: what the collapses themselves do):

- ``d<cells>``: ``facecount.decimate`` to no count, each collapse within that RMS distance of its planes (the
  quadrics ``pipeline.finish.coarsened`` uses);
- ``f<cells>``: ``simplify.collapse_flat`` at that tolerance (every face around a vertex within it of the vertex it
  moves onto).

Per setting: CD, HD, back faces seen, silhouette IoU, normal angle, results with crossing faces, edge-manifold ones,
faces per reference face (mean, median, over 1.5x, within 0.5-1.5x).

    python benchmarks/coarsen_sweep.py --data data/eval-oop --settings d0.25,d0.5,f0.5 SAVED_DIR [SAVED_DIR ...]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from fastmesh.evaluation.eval import _score, _topology_row, artist_vertices
from fastmesh.evaluation.seen import reference_sight, score_sight
from fastmesh.faces.defects import self_intersections
from fastmesh.faces.facecount import decimate
from fastmesh.faces.meshops import remove_unreferenced
from fastmesh.faces.simplify import collapse_flat
from fastmesh.shapes.io import load_shape
from fastmesh.shapes.shape import Normalization
from fastmesh.tokenizer.grid import CELL


def collapsed(vertices: np.ndarray, faces: np.ndarray, setting: str) -> tuple[np.ndarray, np.ndarray]:
    """The mesh collapsed as ``setting`` says ("none", "d<cells>" or "f<cells>")."""
    if setting == "none":
        return vertices, faces
    unit, cells = Normalization.fit(vertices).apply(vertices), float(setting[1:])
    if setting[0] == "d":
        fewer = decimate(unit, faces, 0, max_move=cells * CELL)
    else:
        fewer = collapse_flat(unit, faces, cells * CELL, 1e-10)
    return remove_unreferenced(vertices, fewer)[:2]


def scores(saved: list[Path], data: Path, settings: list[str]) -> dict[str, list[dict]]:
    """Per setting, one row per saved result with a reference: its scores."""
    out: dict[str, list[dict]] = {s: [] for s in settings}
    for ply in sorted(p for d in saved for p in d.glob("*.ply")):
        ref = load_shape(next((data / "reference").glob(f"{ply.stem}.*")))
        result = load_shape(ply)
        artist = artist_vertices(ref, load_shape(data / "inputs" / f"{ply.stem}.npz"))
        cams, views, _ = reference_sight(ref.vertices, ref.faces)
        for s in settings:
            v, f = collapsed(result.vertices, result.faces, s)
            sight = score_sight(v, f, cams, views, len(ref.faces))
            out[s].append({**_score((v, f), ref, artist), **_topology_row(v, f), **sight,
                           "crossing": int(self_intersections(v, f))})
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("saved", nargs="+", type=Path)
    parser.add_argument("--data", type=Path, default=Path("data/eval-oop"))
    parser.add_argument("--settings", default="d0.25,d0.5,d1.0,f0.5,f1.0,f2.0")
    args = parser.parse_args()
    for setting, rows in scores(args.saved, args.data, ["none", *args.settings.split(",")]).items():
        print(f"{setting}: {summary(rows)}")


def summary(rows: list[dict]) -> str:
    def mean(key: str) -> float:
        return float(np.mean([r[key] for r in rows]))

    ratio = np.array([r["faces_per_reference_face"] for r in rows])
    return (f"{len(rows)} results, CD {mean('cd'):.3f} HD {mean('hd'):.2f} back {100 * mean('back_face_share'):.1f} % "
            f"IoU {mean('silhouette_iou'):.3f} angle {mean('normal_angle'):.2f} "
            f"crossing {sum(r['crossing'] > 0 for r in rows)} edge-manifold {sum(r['edge_manifold'] for r in rows)} "
            f"faces / reference {ratio.mean():.2f} (median {np.median(ratio):.2f}, over 1.5x {(ratio > 1.5).sum()}, "
            f"within 0.5-1.5x {((ratio >= 0.5) & (ratio <= 1.5)).sum()})")

if __name__ == "__main__":
    main()
