"""Open inputs through the shipped pipeline (CPU, seed 0): which way their results face, and flat props without a
floor.

- 8 random wavy sheets (tests/test_facing.py's family: any pose, mm to km) as oriented points: the share of the
  result's area facing the way of the input's normals, faces wound against their neighbours.
- 8 flat props without their floor (tests/test_open_plane_cells.py's families: insets, steps, notches, bevels; any
  pose, mm to km) as oriented points: where the result comes from, faces against the truth's, open edges off the
  floor, and the largest exact distance between result and truth both ways, in % of the size.

    python benchmarks/open_props.py
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import trimesh

from fastmesh.faces.defects import winding
from fastmesh.faces.meshops import distance_to_triangles, face_sides, open_sides
from fastmesh.params import GenerateParams
from fastmesh.pipeline import Pipeline
from fastmesh.shapes.shape import Shape

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_facing import _facing_share, _normals, _sheet  # noqa: E402
from test_open_plane_cells import OPEN_FAMILIES, _floorless, _input  # noqa: E402
from test_plane_cells import FAMILIES  # noqa: E402

PARAMS = GenerateParams(seed=0)


def sheets(pipe: Pipeline, rng: np.random.Generator) -> None:
    for i in range(8):
        m = _sheet(rng)
        points, index = trimesh.sample.sample_surface(m, 8192, seed=i)
        normals = _normals(m.vertices, m.faces)[index]
        res = pipe.generate(Shape(vertices=np.asarray(points), normals=normals), PARAMS)
        facing = _facing_share(res.vertices, res.faces, np.asarray(points), normals)
        print(f"sheet {i}: {len(res.faces)} faces ({res.info['result_from']}), facing its input {100 * facing:.1f} % "
              f"of the area, wound against neighbours {winding(res.vertices, res.faces)['misoriented_edges']} edges")


def floorless(pipe: Pipeline, rng: np.random.Generator) -> None:
    for i in range(8):
        family = OPEN_FAMILIES[i % len(OPEN_FAMILIES)]
        truth, floor = _floorless(FAMILIES[family](rng), rng, 10.0 ** rng.uniform(-3, 3))
        size = float(np.ptp(truth.vertices, axis=0).max())
        res = pipe.generate(_input(truth, rng, False), PARAMS)
        v, f = res.vertices, res.faces
        rim = np.unique(face_sides(f)[open_sides(f)])
        off = np.abs(v[rim] @ floor[:3] - floor[3]).max() / size if len(rim) else 0.0
        both = max(distance_to_triangles(trimesh.Trimesh(a, b, process=False).sample(4000, seed=0), c, d).max()
                   for (a, b), (c, d) in (((v, f), (truth.vertices, truth.faces)),
                                          ((truth.vertices, truth.faces), (v, f)))) / size
        print(f"floorless {family}: {len(f)} faces ({res.info['result_from']}) for the truth's {len(truth.faces)}, "
              f"open edges {int(open_sides(f).sum())} (off the floor by {100 * off:.3f} %), distance both ways "
              f"{100 * both:.3f} %")


def main() -> None:
    pipe = Pipeline.from_pretrained(device="cpu", threads=1)
    sheets(pipe, np.random.default_rng(61))
    floorless(pipe, np.random.default_rng(62))


if __name__ == "__main__":
    main()
