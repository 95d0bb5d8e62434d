"""Per mesh, FastMesh against quadric decimation at its face count, from a `fastmesh eval --baseline --json` report.

The means of ``fastmesh eval`` weigh every mesh alike; a user choosing between the two asks per mesh.  This prints
on how many meshes we are closer (CD) and within 1.1x of decimation's CD, and, on the meshes where decimation
reaches our face count (within ``--within`` of it; it stops early on open or non-manifold inputs), both systems'
mean CD and vertex recall (R@1); and how many of our results are the input's decimation itself (the pipeline
returns it where it lies nearer the input).

    fastmesh eval --inputs data/eval-oop-mesh/inputs --reference data/eval-oop-mesh/reference --baseline --json > r.json
    python benchmarks/mesh_vs_decimation.py r.json
"""

from __future__ import annotations

import argparse
import json

import numpy as np


def compare(report: dict, within: float = 0.02) -> dict:
    """The per-mesh comparison of a report's ``fastmesh`` and ``decimation`` rows (meshes where both ran)."""
    rows = [m for m in report["meshes"] if "cd" in m.get("fastmesh", {}) and "cd" in m.get("decimation", {})]
    ours = np.array([m["fastmesh"]["cd"] for m in rows])
    dec = np.array([m["decimation"]["cd"] for m in rows])
    faces = np.array([m["fastmesh"]["faces"] for m in rows])
    reached = np.abs(np.array([m["decimation"]["faces"] for m in rows]) - faces) <= within * faces

    def recall(system: str) -> np.ndarray:
        return np.array([m[system]["vertex_metrics"]["recall_1"] for m in rows])

    out = {"meshes": len(rows), "closer": int((ours < dec).sum()), "within_1_1x": int((ours <= 1.1 * dec).sum()),
           "reached": int(reached.sum()),
           # ours is the input's decimation itself where it lay nearer (``pipeline.result.decimated``)
           "ours_decimated": sum(m["fastmesh"].get("result_from") == "decimated" for m in rows)}
    if reached.any():
        out.update(reached_cd={"fastmesh": float(ours[reached].mean()), "decimation": float(dec[reached].mean())},
                   reached_recall_1={s: float(recall(s)[reached].mean()) for s in ("fastmesh", "decimation")})
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("report", help="the JSON of `fastmesh eval --baseline --json`")
    p.add_argument("--within", type=float, default=0.02, help="decimation reached our count within this share")
    args = p.parse_args()
    with open(args.report) as f:
        print(json.dumps(compare(json.load(f), args.within), indent=1))


if __name__ == "__main__":
    main()
