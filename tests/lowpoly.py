"""Small low-poly meshes made in code, for tests and benchmarks of how a low-poly input comes back.

:func:`two_shells` is a faceted egg exported as two open halves whose rims lie a little apart (a body and a head
modelled separately, never welded); :func:`jittered` a trimesh primitive with its vertices moved off its planes.
"""

from __future__ import annotations

import numpy as np

from fastmesh.shapes.shape import Shape


def _half(segments: int, rings: int, sign: float) -> tuple[np.ndarray, np.ndarray]:
    """An open half egg: a rim of ``segments`` vertices at y = 0, ``rings`` bands above it and a pole fan, wound
    outward; (V, 3) vertices (the rim first) and (F, 3) faces."""
    lat = np.linspace(0.0, np.pi / 2, rings + 2)[1:-1]
    ang = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    rows = [np.stack([np.cos(ang), np.zeros_like(ang), np.sin(ang)], 1)]
    rows += [np.stack([np.cos(ang) * np.cos(a), np.full_like(ang, sign * np.sin(a)), np.sin(ang) * np.cos(a)], 1)
             for a in lat]
    v = np.concatenate(rows + [np.array([[0.0, sign, 0.0]])])
    f = []
    for r in range(rings):
        for i in range(segments):
            j = (i + 1) % segments
            a, b, c, d = r * segments + i, r * segments + j, (r + 1) * segments + i, (r + 1) * segments + j
            f += [[a, c, b], [b, c, d]]
    pole = len(v) - 1
    f += [[rings * segments + i, pole, rings * segments + (i + 1) % segments] for i in range(segments)]
    f = np.array(f, dtype=np.int64)
    return v, (f if sign > 0 else f[:, ::-1])


def two_shells(gap: float = 0.002, segments: int = 26, rings: int = 1, seed: int = 0) -> Shape:
    """A faceted egg (height 2) as two open halves whose equator rims lie ``gap`` x its height apart: 2 x
    ``segments`` open edges, ``segments`` x (2 ``rings`` + 1) faces a half, radii jittered by 5 % (seed ``seed``)
    so that no few planes describe it."""
    rng = np.random.default_rng(seed)
    top_v, top_f = _half(segments, rings, 1.0)
    bottom_v, bottom_f = _half(segments, rings, -1.0)
    top_v = top_v * (1 + 0.05 * rng.standard_normal((len(top_v), 1)))
    bottom_v = bottom_v * (1 + 0.05 * rng.standard_normal((len(bottom_v), 1)))
    bottom_v[:segments] = top_v[:segments]  # one rim, but for the gap
    top_v[:, 1] += 2.0 * gap
    return Shape(vertices=np.concatenate([top_v, bottom_v]), faces=np.concatenate([top_f, bottom_f + len(top_v)]))


def jittered(mesh, scale: float = 0.04, seed: int = 0) -> Shape:
    """A trimesh ``mesh`` as a Shape, each vertex moved radially by ``scale`` x a normal draw (seed ``seed``)."""
    v = np.asarray(mesh.vertices, dtype=np.float64)
    rng = np.random.default_rng(seed)
    return Shape(vertices=v * (1 + scale * rng.standard_normal((len(v), 1))), faces=np.asarray(mesh.faces))
