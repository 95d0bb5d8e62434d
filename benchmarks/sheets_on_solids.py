"""Closed flat parts that carry sheets of their own, through the shipped pipeline (CPU, seed 0): a box with a fin
standing on its top and a box with a sign standing beside it (tests/test_open_sheets.py's ``_box_and_sheet``), 8 of
each, any pose, millimetres to kilometres, as oriented points.  Per prop: how the input was decided and where the
result comes from, its faces against the truth's, edges of more than two faces, faces wound against their
neighbours, and the largest exact distance between result and truth both ways, in % of the size.

    python benchmarks/sheets_on_solids.py
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from open_sheets import row

from fastmesh.evaluation.primitives import point_cloud
from fastmesh.params import GenerateParams
from fastmesh.pipeline import Pipeline
from fastmesh.shapes.shape import Shape

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from poses import posed, random_pose, turned  # noqa: E402
from test_open_sheets import _box_and_sheet  # noqa: E402


def main() -> None:
    pipe = Pipeline.from_pretrained(device="cpu", threads=1)
    for fin in (True, False):
        rng = np.random.default_rng(91 + fin)
        for i in range(8):
            truth, pose = _box_and_sheet(rng, fin), random_pose(rng)
            cloud = point_cloud(truth, seed=i)
            res = pipe.generate(Shape(vertices=posed(cloud.vertices, pose), normals=turned(cloud.normals, pose)),
                                GenerateParams(seed=0))
            source = f"{res.info['result_from']}, decided {res.info['closed_decision']['reason']}"
            print(row(f"{'fin' if fin else 'sign'} {i}", source, res, posed(truth.vertices, pose), truth.faces),
                  flush=True)


if __name__ == "__main__":
    main()
