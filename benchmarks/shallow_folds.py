"""Flat props with faces a few degrees from meeting flat or folding shut, through the pipeline (CPU, seed 0): low
roofs (slopes rising 1-5 degrees) and wedges (2-10 degrees), closed, and open (a house without its floor, a wedge
without its ends), 8 of each, any pose, metres or millimetres far from the origin, as oriented points.  Per prop:
where the result comes from, its faces against the truth's, whether it is wound one way, and the largest distance
from a result vertex to the truth's nearest corner, in % of the size (the corners are the planes' only output).

    python benchmarks/shallow_folds.py
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from fastmesh.evaluation.primitives import point_cloud, posed, random_shape
from fastmesh.params import GenerateParams
from fastmesh.pipeline import Pipeline

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_open_planar import opened  # noqa: E402


def main() -> None:
    pipe = Pipeline.from_pretrained(device="cpu", threads=1)
    for kind in ("low_roof", "wedge"):
        for is_open in (False, True):
            rng = np.random.default_rng(17)
            for i in range(8):
                truth = random_shape(kind, rng)
                truth = posed(opened(truth, kind) if is_open else truth, rng, millimetres=i % 2 == 1)
                res = pipe.generate(point_cloud(truth, seed=i), GenerateParams(seed=0))
                size = float(np.ptp(truth.vertices, axis=0).max())
                off = cKDTree(truth.vertices).query(res.vertices)[0].max() / size
                wound = trimesh.Trimesh(res.vertices, res.faces, process=False).is_winding_consistent
                print(f"{kind}{' open' if is_open else ''} {i}: {len(res.faces)} faces ({res.info['result_from']}) "
                      f"for the truth's {len(truth.faces)}, wound one way {wound}, vertices off the truth's "
                      f"corners {100 * off:.3f} %", flush=True)


if __name__ == "__main__":
    main()
