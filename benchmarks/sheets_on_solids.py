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
import trimesh

from fastmesh.evaluation.primitives import point_cloud
from fastmesh.faces.defects import winding
from fastmesh.faces.meshops import distance_to_triangles, edge_face_counts
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
            v, f, corners = res.vertices, res.faces, posed(truth.vertices, pose)
            both = max(distance_to_triangles(trimesh.Trimesh(a, b, process=False).sample(4000, seed=0), c, d).max()
                       for (a, b), (c, d) in (((v, f), (corners, truth.faces)), ((corners, truth.faces), (v, f))))
            decided = res.info["closed_decision"]
            print(f"{'fin' if fin else 'sign'} {i}: {len(f)} faces ({res.info['result_from']}, decided "
                  f"{decided['reason']}) for the truth's {len(truth.faces)}, edges of 3+ faces "
                  f"{int((edge_face_counts(f) > 2).sum())}, wound against neighbours "
                  f"{winding(v, f)['misoriented_edges']} edges, distance both ways "
                  f"{100 * both / float(np.ptp(corners, axis=0).max()):.3f} %", flush=True)


if __name__ == "__main__":
    main()
