"""Timings of the written result's steps (fastmesh.export.output): quads, the xatlas UV layout, baking a texture at
1,024 x 1,024 and writing each format, for results of 1,280 / 5,120 faces (icospheres) baked from a textured
sphere of 20,000 faces.

Usage: python benchmarks/output_steps.py [--repeat 3]

Prints the median wall time of ``repeat`` runs per step.  Single-threaded; run on an idle machine.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np


def timed(fn, repeat: int) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), out


def textured_sphere():
    """(vertices, faces, SurfaceTexture) of a unit sphere of ~20,000 faces with a checker texture mapped by
    longitude and latitude."""
    import trimesh

    from fastmesh.shapes.texture import SurfaceTexture

    m = trimesh.creation.icosphere(5)
    v = np.asarray(m.vertices)
    uv = np.stack([0.5 + np.arctan2(v[:, 2], v[:, 0]) / (2 * np.pi), 0.5 + np.arcsin(np.clip(v[:, 1], -1, 1)) / np.pi],
                  axis=1)
    checker = ((np.arange(512)[:, None] // 32 + np.arange(512)[None, :] // 32) % 2).astype(np.uint8) * 200 + 40
    image = np.dstack([checker, 255 - checker, np.full_like(checker, 128), np.full_like(checker, 255)])
    tex = SurfaceTexture(uv=uv, image_of=np.zeros(len(v), np.int64), images=[image], factors=np.ones((1, 4)))
    return v, np.asarray(m.faces), tex


def main() -> None:
    import trimesh

    from fastmesh.export.bake import bake
    from fastmesh.export.layout import uv_layout
    from fastmesh.export.output import MeshOut
    from fastmesh.export.quads import pair_triangles

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    src_v, src_f, tex = textured_sphere()
    print(f"{'faces':>6} {'quads':>7} {'uv':>7} {'bake':>7} {'glb':>7} {'obj':>7} {'ply':>7}  quad share")
    for sub in (3, 4):
        m = trimesh.creation.icosphere(sub)
        v, f = np.asarray(m.vertices), np.asarray(m.faces)
        t_quads, pairs = timed(lambda v=v, f=f: pair_triangles(v, f), args.repeat)
        t_uv, lay = timed(lambda v=v, f=f: uv_layout(v, f), args.repeat)
        t_bake, image = timed(lambda v=v, f=f, lay=lay: bake(v, f, lay, src_v, src_f, tex), args.repeat)
        out = MeshOut(vertices=v, faces=f, pairs=pairs, layout=lay, texture=image)
        t_fmt = [timed(lambda fmt=fmt, out=out: out.export(fmt), args.repeat)[0] for fmt in ("glb", "obj", "ply")]
        share = out.counts()["quad_share"]
        print(f"{len(f):>6} " + " ".join(f"{t:6.2f}s" for t in (t_quads, t_uv, t_bake, *t_fmt)) + f"  {share:.2f}")


if __name__ == "__main__":
    main()
