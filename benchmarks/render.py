"""Timings of the preview renderer (fastmesh.preview.render).  Target: < 0.5 s for 5,000 faces at 512 px.

Usage: python benchmarks/render.py [--size 512] [--repeat 5] [--corpus ../shared/corpus]

Prints the median and best wall time of ``repeat`` runs for icospheres of 1,280 / 5,120 /
20,480 faces (uniform small triangles: the common case for generated meshes), for real
corpus meshes near 1k / 5k faces when the corpus is present, for point clouds, and for
PNG encoding.  Single-threaded numpy; run on an idle machine for stable figures.
"""

from __future__ import annotations

import argparse
import csv
import statistics
import time
from pathlib import Path

import numpy as np


def timed(fn, repeat: int) -> tuple[float, float, object]:
    out = fn()  # warm-up (imports, allocator)
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), min(times), out


def corpus_meshes(root: Path, targets=(1000, 5000)) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """The corpus mesh whose face count is closest to each target (largest corpus meshes ~8k faces)."""
    import trimesh

    manifest = root / "manifest.csv"
    if not manifest.exists():
        return []
    rows = [r for r in csv.DictReader(manifest.open()) if r["kind"] == "mesh"]
    out = []
    for target in targets:
        r = min(rows, key=lambda r: abs(int(r["faces"]) - target))
        m = trimesh.load(root / r["file"], process=False)
        out.append((Path(r["file"]).name[:48], np.asarray(m.vertices), np.asarray(m.faces)))
    return out


def main() -> None:
    import trimesh

    from fastmesh.preview.render import render_mesh, render_points, to_png

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--corpus", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "corpus")
    args = ap.parse_args()

    scenes = [(f"icosphere({s})", np.asarray(m.vertices), np.asarray(m.faces))
              for s in (3, 4, 5) for m in [trimesh.creation.icosphere(subdivisions=s)]]
    scenes += corpus_meshes(args.corpus)
    print(f"render_mesh at {args.size} px, median / best of {args.repeat} (seconds)")
    print(f"{'mesh':50s} {'faces':>7s} {'shaded':>15s} {'+wireframe':>15s}")
    last = None
    for name, v, f in scenes:
        cells = []
        for wf in (False, True):
            med, best, last = timed(lambda v=v, f=f, wf=wf: render_mesh(v, f, args.size, wireframe=wf), args.repeat)
            cells.append(f"{med:6.3f} / {best:6.3f}")
        print(f"{name:50s} {len(f):7d} {cells[0]:>15s} {cells[1]:>15s}")

    print(f"\nrender_points at {args.size} px (sphere samples with normals)")
    rng = np.random.default_rng(0)
    for n in (10_000, 100_000):
        p = rng.normal(size=(n, 3))
        p /= np.linalg.norm(p, axis=1, keepdims=True)
        med, best, _ = timed(lambda p=p: render_points(p, normals=p, size=args.size), args.repeat)
        print(f"{n:7d} points: {med:6.3f} / {best:6.3f}")

    med, best, png = timed(lambda: to_png(last), args.repeat)
    print(f"\nto_png of the last wireframe image: {med:6.3f} / {best:6.3f} s, {len(png) / 1024:.1f} KiB")


if __name__ == "__main__":
    main()
