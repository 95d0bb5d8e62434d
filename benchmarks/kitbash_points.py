"""Kitbashed props as point clouds through the shipped pipeline (CPU, seed 0), beside screened Poisson + decimation
to our face count: 32 random props of 3-7 boxes that touch or overlap (tests/test_kitbash.py's family), any pose,
millimetres to kilometres, each as 8,192 oriented points of its outside (what a scan sees: no face hidden inside
another part).  Per prop, for ours and the anchor: faces (the true union's beside them), faces wound against their
neighbours, faces crossing another, the back faces 14 views see, the silhouette overlap and normal angle against
the union, and the largest exact distance between the result and the union both ways, in % of the size.  Exact:
within the planes path's tolerance (2e-4 of the size) both ways.

    python benchmarks/kitbash_points.py
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import trimesh

from fastmesh.evaluation.baselines import poisson
from fastmesh.evaluation.visible import visible_report
from fastmesh.faces.crossings import crossing_faces
from fastmesh.faces.defects import winding
from fastmesh.faces.kitbash import kitbash_union
from fastmesh.faces.meshops import distance_to_triangles
from fastmesh.params import GenerateParams
from fastmesh.pipeline import Pipeline
from fastmesh.shapes.shape import Normalization, Shape

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_kitbash import _joined, _outside_points, _posed, _random_prop  # noqa: E402


def both_ways(v: np.ndarray, f: np.ndarray, union: tuple[np.ndarray, np.ndarray], size: float) -> float:
    """Largest exact distance between a mesh and the union (4,000 samples of each to the other), / ``size``."""
    a = trimesh.Trimesh(v, f, process=False).sample(4000, seed=0)
    b = trimesh.Trimesh(*union, process=False).sample(4000, seed=0)
    return max(distance_to_triangles(a, *union).max(), distance_to_triangles(b, v, f).max()) / size


def measures(v: np.ndarray, f: np.ndarray, union: tuple[np.ndarray, np.ndarray], size: float) -> tuple[str, float]:
    """One mesh's figures against the ``union``, and its distance both ways (a share of ``size``)."""
    seen = visible_report(v, f, union)
    off = both_ways(v, f, union, size)
    return (f"{len(f)} faces, wound against neighbours {winding(v, f)['misoriented_edges']} edges, crossing "
            f"{int(crossing_faces(v, f).sum())}, back faces seen "
            f"{100 * seen['back_face_share']:.1f} %, silhouette {seen['silhouette_iou']:.3f}, normal angle "
            f"{seen['normal_angle']:.1f} deg, distance both ways {100 * off:.3f} %"), off


def main() -> None:
    pipe = Pipeline.from_pretrained(device="cpu", threads=1)
    rng = np.random.default_rng(57)
    exact = 0
    for i in range(32):
        parts = _posed(_random_prop(rng), rng, (1e-3, 1.0, 1e3)[i % 3])
        points, normals = _outside_points(parts, 8192, rng)
        vertices, faces = _joined(parts)
        norm = Normalization.fit(vertices)
        found = kitbash_union(norm.apply(vertices), faces)
        union, size = (norm.invert(found[0]), found[1]), float(np.ptp(vertices, axis=0).max())
        start = time.perf_counter()
        res = pipe.generate(Shape(vertices=points, normals=normals), GenerateParams(seed=0))
        took = time.perf_counter() - start
        ours, off = measures(res.vertices, res.faces, union, size)
        exact += off < 2e-4
        print(f"prop {i} ({len(parts)} parts, the union's {len(union[1])} faces): ours from "
              f"{res.info['result_from']} in {took:.1f} s: {ours}", flush=True)
        anchor, _ = measures(*poisson(Shape(vertices=points, normals=normals), len(res.faces)), union, size)
        print(f"  Poisson + decimation to our count: {anchor}", flush=True)
    print(f"exact (within 2e-4 of the size both ways): {exact} / 32")


if __name__ == "__main__":
    main()
