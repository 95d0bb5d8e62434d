"""A UV layout of a triangle mesh, made by xatlas (charts cut along sharp edges and seams, flattened with
little stretch, packed into the unit square without overlap), and the texels each triangle covers.

UV coordinates follow OBJ's and OpenGL's convention: u to the right, v up from the image's bottom row; a
texel at image row ``r`` and column ``c`` of an ``H`` x ``W`` image has its centre at
``((c + 0.5) / W, 1 - (r + 0.5) / H)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

TEXTURE_SIZE = 1024  # texels a side of the atlas the layout is packed for (and a baked texture has)
PADDING = 2  # texels between charts, so a texture sampled with filtering does not bleed across them
RASTER_BLOCK = 1 << 21  # candidate texels tested at once (bounds the rasteriser's memory)


@dataclass
class UVLayout:
    """A UV layout of a mesh whose vertices are split along the seams.

    Attributes
    ----------
    uv : (W, 2) float64
        UV coordinates in [0, 1].
    faces : (F, 3) int64
        Per triangle of the mesh, the rows of ``uv`` at its corners.
    vertex : (W,) int64
        The mesh vertex each UV vertex belongs to.
    size : int
        Texels a side of the atlas the charts were packed for.
    """

    uv: np.ndarray
    faces: np.ndarray
    vertex: np.ndarray
    size: int = TEXTURE_SIZE


def uv_layout(vertices: np.ndarray, faces: np.ndarray, size: int = TEXTURE_SIZE) -> UVLayout:
    """A UV layout of the triangles ``faces`` at ``vertices`` made by xatlas, packed for a ``size`` x ``size``
    texture with :data:`PADDING` texels between charts.

    Parameters
    ----------
    vertices : (V, 3) float
    faces : (F, 3) int

    Returns
    -------
    UVLayout
        Its ``faces`` row ``f`` is mesh triangle ``f``.
    """
    import xatlas

    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    # xatlas reads float32: in the unit cube, where float32 keeps a far-off mesh's detail.
    lo, hi = v.min(axis=0), v.max(axis=0)
    unit = ((v - (lo + hi) / 2) / max(float((hi - lo).max()), 1e-300)).astype(np.float32)
    atlas = xatlas.Atlas()
    atlas.add_mesh(unit, f.astype(np.uint32))
    pack = xatlas.PackOptions()
    pack.resolution, pack.padding, pack.bilinear = int(size), PADDING, True
    atlas.generate(xatlas.ChartOptions(), pack)
    if atlas.atlas_count != 1:  # the charts did not fit one atlas of that size: one atlas of the size they need
        atlas = xatlas.Atlas()
        atlas.add_mesh(unit, f.astype(np.uint32))
        pack.resolution = 0
        atlas.generate(xatlas.ChartOptions(), pack)
    vmap, index, uv = atlas[0]
    return UVLayout(uv=np.clip(np.asarray(uv, dtype=np.float64), 0.0, 1.0),
                    faces=np.asarray(index, dtype=np.int64).reshape(-1, 3),
                    vertex=np.asarray(vmap, dtype=np.int64), size=int(size))


def rasterize(uv: np.ndarray, faces: np.ndarray, size: int, inset: float = 0.0
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every texel centre of a ``size`` x ``size`` image inside each triangle of a layout.

    Parameters
    ----------
    uv : (W, 2) float
    faces : (F, 3) int, rows of ``uv``
    inset : float
        Texels a centre must lie inside every edge (0: on an edge counts; shared edges then count twice).

    Returns
    -------
    face : (N,) int64
        The triangle of each hit (a texel inside two triangles is two hits).
    texel : (N,) int64
        ``row * size + column`` of the hit.
    bary : (N, 3) float64
        Its barycentric coordinates in the triangle.
    """
    x = np.asarray(uv, dtype=np.float64)[:, 0] * size - 0.5  # texel column whose centre is there
    y = (1.0 - np.asarray(uv, dtype=np.float64)[:, 1]) * size - 0.5
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    fx, fy = x[faces], y[faces]
    area2 = (fx[:, 1] - fx[:, 0]) * (fy[:, 2] - fy[:, 0]) - (fx[:, 2] - fx[:, 0]) * (fy[:, 1] - fy[:, 0])
    x0 = np.clip(np.ceil(fx.min(axis=1)), 0, size).astype(np.int64)
    x1 = np.clip(np.floor(fx.max(axis=1)), -1, size - 1).astype(np.int64)
    y0 = np.clip(np.ceil(fy.min(axis=1)), 0, size).astype(np.int64)
    y1 = np.clip(np.floor(fy.max(axis=1)), -1, size - 1).astype(np.int64)
    w, h = np.maximum(x1 - x0 + 1, 0), np.maximum(y1 - y0 + 1, 0)
    live = np.flatnonzero((w > 0) & (h > 0) & (np.abs(area2) > 1e-12))
    edges = np.stack([np.hypot(fx[:, (k + 2) % 3] - fx[:, (k + 1) % 3], fy[:, (k + 2) % 3] - fy[:, (k + 1) % 3])
                      for k in range(3)], axis=1)  # edge k is the one opposite corner k
    out_f, out_t, out_b = [], [], []
    counts = (w * h)[live]
    ends = np.cumsum(counts)
    start = 0
    while start < len(live):  # blocks of triangles with at most RASTER_BLOCK candidate texels together
        stop = max(start + 1, int(np.searchsorted(ends, (ends[start - 1] if start else 0) + RASTER_BLOCK)))
        tri = live[start:stop]
        n = counts[start:stop]
        t = np.repeat(tri, n)
        local = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
        px, py = x0[t] + local % w[t], y0[t] + local // w[t]
        b = _barycentric(fx[t], fy[t], area2[t], px, py)
        # A barycentric coordinate is the distance to its edge over the triangle's height on that edge.
        inside = np.ones(len(t), dtype=bool)
        for k in range(3):
            low = -1e-9 if inset == 0 else inset * edges[t, k] / np.abs(area2[t])
            inside &= b[:, k] >= low
        out_f.append(t[inside])
        out_t.append(py[inside] * size + px[inside])
        out_b.append(b[inside])
        start = stop
    if not out_f:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3))
    return np.concatenate(out_f), np.concatenate(out_t), np.concatenate(out_b)


def _barycentric(fx: np.ndarray, fy: np.ndarray, area2: np.ndarray, px: np.ndarray, py: np.ndarray) -> np.ndarray:
    """(N, 3) barycentric coordinates of points ``(px, py)`` in triangles of corners ``fx``, ``fy`` (N, 3) with
    twice their signed areas ``area2`` (N,)."""
    out = np.empty((len(px), 3))
    for k in range(3):
        j, m = (k + 1) % 3, (k + 2) % 3
        out[:, k] = ((fx[:, j] - px) * (fy[:, m] - py) - (fx[:, m] - px) * (fy[:, j] - py)) / area2
    return out


def overlap_share(uv: np.ndarray, faces: np.ndarray, size: int = 512) -> float:
    """The share of the texels a layout covers that two or more of its triangles cover, each at least half a
    texel inside its edges (so triangles that only share an edge do not count): 0 for a layout without
    overlap.

    Parameters
    ----------
    uv : (W, 2) float
    faces : (F, 3) int, rows of ``uv``
    """
    _, texel, _ = rasterize(uv, faces, size, inset=0.5)
    if len(texel) == 0:
        return 0.0
    hits = np.bincount(texel, minlength=size * size)
    return float(np.count_nonzero(hits > 1) / np.count_nonzero(hits))
