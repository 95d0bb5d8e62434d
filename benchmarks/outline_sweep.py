"""Tolerances of ``faces.outline.outlined`` on saved results: faces per reference face and the fits it costs.

Reads the results ``fastmesh eval --save DIR`` wrote (``DIR/<name>.ply``, in the input's frame), the inputs' points
and the references of the eval set, and for each setting cuts every result's flat regions from their outlines (in
the unit cube of the input's points, as the pipeline does): faces per reference face (mean; over 1.5x), the
outlined mesh's ``support.weighed_fit`` over the result's against the input's points, and, for each margin, the
results the pipeline would keep (``pipeline.finish.FEWER_FACES_MARGIN``) and what they give.

    python benchmarks/outline_sweep.py --data data/eval-oop SAVED_DIR [SAVED_DIR ...]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import trimesh

from fastmesh.faces.outline import OutlineConfig, outlined
from fastmesh.faces.support import weighed_fit
from fastmesh.tokenizer.grid import CELL

SETTINGS = [OutlineConfig(10.0, 0.5 * CELL), OutlineConfig(15.0, 0.5 * CELL), OutlineConfig(10.0, CELL),
            OutlineConfig(15.0, CELL)]
MARGINS = (1.02, 1.05, 1.1)


def rows(saved: list[Path], data: Path) -> list[list[float]]:
    """Per saved result: its faces per reference face, then per setting the outlined mesh's and its fit ratio."""
    out = []
    for ply in sorted(p for d in saved for p in d.glob("*.ply")):
        result = trimesh.load(ply, process=False)
        points = np.load(data / "inputs" / f"{ply.stem}.npz")["points"]
        reference = next((data / "reference").glob(f"{ply.stem}.*"))
        faces = len(trimesh.load(reference, process=False, force="mesh").faces)
        low, size = points.min(0), float(np.ptp(points, axis=0).max())
        v, unit = (np.asarray(result.vertices) - low) / size, (points - low) / size
        f = np.asarray(result.faces)
        base = weighed_fit(v, f, unit)
        row = [len(f) / faces]
        for cfg in SETTINGS:
            v2, f2, _ = outlined(v, f, cfg)
            row += [len(f2) / faces, weighed_fit(v2, f2, unit) / base]
        out.append(row)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("saved", nargs="+", type=Path)
    parser.add_argument("--data", type=Path, default=Path("data/eval-oop"))
    args = parser.parse_args()
    r = np.array(rows(args.saved, args.data))
    print(f"{len(r)} results: faces / reference mean {r[:, 0].mean():.3f}, over 1.5x {(r[:, 0] > 1.5).sum()}")
    for k, cfg in enumerate(SETTINGS):
        ratio, fit = r[:, 1 + 2 * k], r[:, 2 + 2 * k]
        print(f"{cfg.degrees:.0f} deg, {cfg.tol / CELL:.1f} cell: faces / reference {ratio.mean():.3f} "
              f"(over 1.5x {(ratio > 1.5).sum()}), fit ratio mean {fit.mean():.3f} max {fit.max():.3f}")
        for margin in MARGINS:
            kept = fit <= margin
            final = np.where(kept, ratio, r[:, 0])
            print(f"    margin {margin}: {kept.sum()} kept, faces / reference {final.mean():.3f} "
                  f"(over 1.5x {(final > 1.5).sum()}), fit ratio of those kept {fit[kept].mean():.4f}")


if __name__ == "__main__":
    main()
