"""Mixed props as dense meshes, through the shipped pipeline (CPU, seed 0), beside what a user would do instead:
a box with one or two round parts on it (tests/test_mixed_meshes.py's family), 8 of them, any pose, millimetres to
kilometres, every other one stored inside out, split into 10,000-60,000 faces.  Per prop, for ours and for the
input's quadric decimation to our face count: where ours comes from, faces against the truth's, edges of more than
two faces, faces wound against their neighbours, the back faces 14 views see, the silhouette overlap and normal
angle against the truth, and the largest exact distance between it and the truth both ways, in % of the size.

    python benchmarks/mixed_meshes.py
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from fastmesh.evaluation.visible import visible_report
from fastmesh.faces.decimation import quadric_decimation
from fastmesh.faces.defects import winding
from fastmesh.faces.meshops import edge_face_counts
from fastmesh.params import GenerateParams
from fastmesh.pipeline import Pipeline
from fastmesh.shapes.shape import Shape

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from poses import posed, random_pose  # noqa: E402
from test_mixed_meshes import both_ways, dense, mixed_prop  # noqa: E402


def measures(v: np.ndarray, f: np.ndarray, truth: Shape) -> str:
    """One mesh's figures against ``truth``."""
    seen = visible_report(v, f, (truth.vertices, truth.faces))
    size = float(np.ptp(truth.vertices, axis=0).max())
    return (f"{len(f)} faces, edges of 3+ faces {int((edge_face_counts(f) > 2).sum())}, wound against neighbours "
            f"{winding(v, f)['misoriented_edges']} edges, back faces seen {100 * seen['back_face_share']:.1f} %, "
            f"silhouette {seen['silhouette_iou']:.3f}, normal angle {seen['normal_angle']:.1f} deg, distance both "
            f"ways {100 * both_ways(v, f, truth) / size:.3f} %")


def main() -> None:
    pipe = Pipeline.from_pretrained(device="cpu", threads=1)
    rng = np.random.default_rng(2026)
    for i in range(8):
        unit, pose = mixed_prop(rng), random_pose(rng)
        v, f = dense(unit, rng)
        f = f[:, ::-1] if i % 2 else f
        truth = Shape(vertices=posed(unit.vertices, pose), faces=unit.faces)
        start = time.perf_counter()
        res = pipe.generate(Shape(vertices=posed(v, pose), faces=f), GenerateParams(seed=0))
        took = time.perf_counter() - start
        print(f"prop {i} ({len(f)} faces in, the truth's {len(unit.faces)}): ours from {res.info['result_from']} in "
              f"{took:.1f} s: {measures(res.vertices, res.faces, truth)}", flush=True)
        # in the family's own frame (about 1 across): the decimation reads no units
        print(f"  decimation to our count: {measures(*quadric_decimation(v, f, len(res.faces)), unit)}", flush=True)


if __name__ == "__main__":
    main()
