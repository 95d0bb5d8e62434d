"""What the networks make of low-poly mesh inputs: the face count of their result before the low-poly check, and
whether the input came back as itself after them (``fastmesh.pipeline.result.FEW_FACES`` is set from it).

    python benchmarks/low_poly.py [--seeds 0 1]

Runs the shipped weights with ``FEW_FACES`` = 0 (every input goes through the networks) on a faceted egg of 1-3
bands a half (156, 260, 364 faces), jittered icospheres (80, 320), a capsule (128), a cone (24), a torus (144) and a
cylinder (64), and prints one JSON line per input and seed: its faces, the networks' result's faces (``whole``'s
count), where the result came from, and the seconds.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch
import trimesh

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from lowpoly import jittered, two_shells  # noqa: E402

from fastmesh.params import GenerateParams  # noqa: E402
from fastmesh.pipeline import Pipeline  # noqa: E402
from fastmesh.pipeline import result as step8  # noqa: E402


def inputs() -> dict:
    cases = {f"egg{r}": two_shells(gap=0.0, rings=r) for r in (1, 2, 3)}
    cases.update({f"ico{k}": jittered(trimesh.creation.icosphere(k)) for k in (1, 2)})
    cases["capsule"] = jittered(trimesh.creation.capsule(height=2.0, radius=0.5, count=[8, 8]))
    cases["cone"] = jittered(trimesh.creation.cone(1.0, 2.0, sections=12))
    cases["torus"] = jittered(trimesh.creation.torus(1.0, 0.3, major_sections=12, minor_sections=6))
    cases["cylinder"] = jittered(trimesh.creation.cylinder(0.5, 2.0, sections=16))
    return cases


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    args = ap.parse_args()
    torch.set_num_threads(1)
    counts: list[int] = []
    low_poly = step8.low_poly

    def counted(shape, faces):  # ``whole`` asks with the networks' face count
        counts.append(int(faces))
        return low_poly(shape, faces)

    step8.low_poly, step8.FEW_FACES = counted, 0
    pipe = Pipeline.from_pretrained()
    for name, shape in inputs().items():
        for seed in args.seeds:
            counts.clear()
            t = time.perf_counter()
            res = pipe.generate(shape, GenerateParams(seed=seed))
            print(json.dumps({"name": name, "seed": seed, "input_faces": len(shape.faces),
                              "network_faces": counts[1] if len(counts) > 1 else None,
                              "result_from": res.info["result_from"], "faces": len(res.faces),
                              "seconds": round(time.perf_counter() - t, 1)}), flush=True)


if __name__ == "__main__":
    main()
