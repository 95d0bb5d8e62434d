"""Props built from flat parts through the shipped pipeline (CPU, seed 0).

- 8 random kitbashed props (3-7 boxes that touch or overlap, any pose, mm to km), scored against their true union by
  exact point-to-triangle distances both ways; pass: closed, one piece, no face hidden inside a part, within 1e-6 of
  the prop's size.
- 6 random boxes scanned with 0.3 % noise, as a dense mesh and as bare points; pass: 12 faces, closed.
- 6 faceted cylinders of 16-48 sides from their meshes; pass: closed, within 1 % of the size both ways.

The shapes are the test families' own (tests/test_kitbash.py, tests/test_noisy_flats.py).

    python benchmarks/flat_parts.py
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import trimesh

from fastmesh.evaluation.primitives import posed, random_shape
from fastmesh.faces.meshops import distance_to_triangles
from fastmesh.params import GenerateParams
from fastmesh.pipeline import Pipeline
from fastmesh.shapes.shape import Shape

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_kitbash import _inside_parts, _joined, _posed, _random_prop, _sample  # noqa: E402
from test_noisy_flats import _scan  # noqa: E402

PARAMS = GenerateParams(seed=0)


def both_ways(res_v, res_f, ref_v, ref_f, size: float, rng) -> float:
    """Largest exact distance between the two surfaces (samples of each to the other's triangles), / ``size``."""
    a = trimesh.Trimesh(res_v, res_f, process=False).sample(4000, seed=int(rng.integers(1 << 31)))
    b = trimesh.Trimesh(ref_v, ref_f, process=False).sample(4000, seed=int(rng.integers(1 << 31)))
    return max(distance_to_triangles(a, ref_v, ref_f).max(), distance_to_triangles(b, res_v, res_f).max()) / size


def kitbash(pipe: Pipeline, rng) -> int:
    passed = 0
    for i in range(8):
        parts = _posed(_random_prop(rng), rng, (1e-3, 1.0, 1e3)[i % 3])
        v, f = _joined(parts)
        size = np.ptp(v, 0).max()
        res = pipe.generate(Shape(vertices=v, faces=f), PARAMS)
        m = trimesh.Trimesh(res.vertices, res.faces, process=False)
        s, n = _sample(m, 4000, rng)
        on = distance_to_triangles(s, v, f).max() / size
        hidden = int(_inside_parts(s + 1e-6 * size * n, parts).sum())
        outer = [_sample(p, 2000, rng) for p in parts]
        outer = np.vstack([q[~_inside_parts(q + 1e-6 * size * nn, parts)] for q, nn in outer])
        back = distance_to_triangles(outer, m.vertices, m.faces).max() / size
        ok = res.quality["watertight"] and res.quality["components"] == 1 and hidden == 0 and max(on, back) < 1e-6
        passed += ok
        print(f"kitbash {i}: {len(parts)} parts, {len(f)} faces -> {len(res.faces)} ({res.info['result_from']}), "
              f"watertight {res.quality['watertight']}, pieces {res.quality['components']}, hidden {hidden}, "
              f"distance {max(on, back):.1e}, pass {ok}")
    return passed


def noisy_boxes(pipe: Pipeline, rng) -> int:
    passed = 0
    for i in range(6):
        box = posed(random_shape("box", rng), rng, turn=True, millimetres=i % 2 == 1)
        size = np.ptp(box.vertices, 0).max()
        for dense in (True, False):
            res = pipe.generate(_scan(box, 0.003, rng, dense), PARAMS)
            hd = both_ways(res.vertices, res.faces, box.vertices, box.faces, size, rng)
            ok = len(res.faces) == 12 and res.quality["watertight"]
            passed += ok
            print(f"noisy box {i} ({'dense' if dense else 'points'}): {len(res.faces)} faces "
                  f"({res.info['result_from']}), HD {100 * hd:.2f} % of size, pass {ok}")
    return passed


def cylinders(pipe: Pipeline, rng) -> int:
    passed = 0
    for _ in range(6):
        sides = int(rng.integers(16, 49))
        tm = trimesh.creation.cylinder(rng.uniform(0.2, 1), rng.uniform(0.2, 2), sections=sides)
        tm.apply_transform(trimesh.transformations.random_rotation_matrix(rng.random(3)))
        v, f = np.asarray(tm.vertices), np.asarray(tm.faces)
        res = pipe.generate(Shape(vertices=v, faces=f), PARAMS)
        hd = both_ways(res.vertices, res.faces, v, f, np.ptp(v, 0).max(), rng)
        ok = hd < 0.01 and res.quality["watertight"]
        passed += ok
        print(f"cylinder, {sides} sides ({len(f)} faces): {len(res.faces)} faces ({res.info['result_from']}), "
              f"HD {100 * hd:.4f} %, pass {ok}")
    return passed


def main() -> None:
    pipe = Pipeline.from_pretrained(device="cpu", threads=1)
    rng = np.random.default_rng(52)
    k, b, c = kitbash(pipe, rng), noisy_boxes(pipe, rng), cylinders(pipe, rng)
    print(f"kitbashed props {k} / 8, noisy boxes {b} / 12, faceted cylinders {c} / 6")


if __name__ == "__main__":
    main()
