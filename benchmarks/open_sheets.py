"""Open flat props built from sheets that end inside their box, through the shipped pipeline (CPU, seed 0):
tests/test_open_sheets.py's families (a panel set into a frame open at the back; a shelf open at the front with one
to three boards, reaching its opening or short of it; a ledge standing out of a wall, its front square, cut at an
angle, skewed a few degrees off square or its board warped (folded 1.5-5 degrees along a diagonal); a gusset
standing on a floor against a wall), 8 of each, any pose, millimetres to kilometres, as oriented points, or with
``--noise`` scanned as bare points. Per prop: where the result comes from, its faces against the truth's, edges of
more than two faces, faces wound against their neighbours, and the largest exact distance between result and truth
both ways, in % of the size.

    python benchmarks/open_sheets.py
    python benchmarks/open_sheets.py --noise 0.003
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import trimesh

from fastmesh.evaluation.primitives import point_cloud
from fastmesh.faces.defects import winding
from fastmesh.faces.meshops import distance_to_triangles, edge_face_counts
from fastmesh.params import GenerateParams
from fastmesh.pipeline import Pipeline
from fastmesh.shapes.io import with_normals
from fastmesh.shapes.shape import Shape

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from poses import posed, random_pose, turned  # noqa: E402
from test_open_sheets import FAMILIES  # noqa: E402


def _input(truth: Shape, pose: tuple, i: int, noise: float, rng: np.random.Generator) -> Shape:
    """``truth`` as 8,192 oriented points, or scanned: with ``noise`` times its size of Gaussian noise, bare points
    (no normals, as a scanner's XYZ file is read)."""
    cloud = point_cloud(truth, seed=i)
    if not noise:
        return Shape(vertices=posed(cloud.vertices, pose), normals=turned(cloud.normals, pose))
    size = float(np.ptp(truth.vertices, axis=0).max())
    return with_normals(Shape(vertices=posed(cloud.vertices + rng.normal(0, noise * size, (8192, 3)), pose)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--noise", type=float, default=0.0, help="scan noise, a share of the size (0.003: 0.3 %%)")
    noise = parser.parse_args().noise
    pipe = Pipeline.from_pretrained(device="cpu", threads=1)
    rng = np.random.default_rng(73)
    scans = np.random.default_rng(79)  # apart, so that the shapes drawn are the same with and without noise
    for family in sorted(FAMILIES):
        for i in range(8):
            truth = FAMILIES[family](rng)
            pose = random_pose(rng)
            res = pipe.generate(_input(truth, pose, i, noise, scans), GenerateParams(seed=0))
            print(row(f"{family} {i}", res.info["result_from"], res, posed(truth.vertices, pose), truth.faces),
                  flush=True)


def row(label: str, source: str, res, corners: np.ndarray, faces: np.ndarray) -> str:
    """One prop's line: its faces from ``source`` against the truth's (``corners``, ``faces``), edges of more than
    two faces, faces wound against their neighbours, the largest exact distance between them both ways in %."""
    v, f = res.vertices, res.faces
    both = max(distance_to_triangles(trimesh.Trimesh(a, b, process=False).sample(4000, seed=0), c, d).max()
               for (a, b), (c, d) in (((v, f), (corners, faces)), ((corners, faces), (v, f))))
    return (f"{label}: {len(f)} faces ({source}) for the truth's {len(faces)}, edges of 3+ faces "
            f"{int((edge_face_counts(f) > 2).sum())}, wound against neighbours {winding(v, f)['misoriented_edges']} "
            f"edges, distance both ways {100 * both / float(np.ptp(corners, axis=0).max()):.3f} %")


if __name__ == "__main__":
    main()
