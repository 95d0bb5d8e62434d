"""A textured input's base colour transferred onto a result's UV layout (``bake=true``).

Each texel of the result's atlas lies on one of its triangles; its colour is the input's at the nearest point
of the input's surface (the input's UVs there, its texture sampled bilinearly, times the material's base
colour factor).  Texels between charts take their nearest chart's colour, so filtering does not bleed the
background into the seams.
"""

from __future__ import annotations

import numpy as np

from ..faces.meshops import closest_on_triangles
from ..shapes.texture import SurfaceTexture
from .layout import UVLayout, rasterize

MAX_SAMPLES = 500_000  # samples of the input surface that locate each texel's nearest input triangle


def nearest_points(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, spacing: float,
                   seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The nearest point of a triangle mesh to each of ``points``: on the triangle of the nearest of the mesh's
    surface samples (its triangles' centres and area-weighted samples ``spacing`` apart, at most
    :data:`MAX_SAMPLES`), the point of that triangle nearest.

    Parameters
    ----------
    points : (N, 3) float
    vertices : (V, 3) float
    faces : (F, 3) int
    spacing : float
        Distance between the samples (the result's texel size serves).

    Returns
    -------
    face : (N,) int64, the triangle of each nearest point
    bary : (N, 3) float64, its barycentric coordinates there
    """
    from scipy.spatial import cKDTree

    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces, dtype=np.int64)]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    n = int(min(MAX_SAMPLES, area.sum() / max(spacing, 1e-300) ** 2))
    rng = np.random.default_rng(seed)
    drawn = rng.choice(len(tri), size=n, p=area / area.sum()) if n > 0 and area.sum() > 0 else np.zeros(0, np.int64)
    r1, r2 = np.sqrt(rng.random(n))[:, None], rng.random(n)[:, None]
    samples = np.concatenate([tri.mean(axis=1), (1 - r1) * tri[drawn, 0] + r1 * (1 - r2) * tri[drawn, 1]
                              + r1 * r2 * tri[drawn, 2]])
    owner = np.concatenate([np.arange(len(tri)), drawn])
    face = owner[cKDTree(samples).query(np.asarray(points, dtype=np.float64))[1]]
    return face, closest_on_triangles(np.asarray(points, dtype=np.float64), tri[face])


def sample(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(N, 4) float colours (0..255) of an RGBA ``image`` (H, W, 4) at ``uv`` (N, 2), bilinear, the texture
    repeating outside [0, 1] (glTF's default wrap)."""
    h, w = image.shape[:2]
    x = (np.asarray(uv[:, 0]) % 1.0) * w - 0.5
    y = (1.0 - np.asarray(uv[:, 1]) % 1.0) * h - 0.5
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    tx, ty = (x - x0)[:, None], (y - y0)[:, None]

    def at(r, c):  # gathered before converting: the whole image in float64 would be 32 bytes a texel
        return image[r % h, c % w].astype(np.float64)

    return ((1 - ty) * ((1 - tx) * at(y0, x0) + tx * at(y0, x0 + 1))
            + ty * ((1 - tx) * at(y0 + 1, x0) + tx * at(y0 + 1, x0 + 1)))


def bake(vertices: np.ndarray, faces: np.ndarray, layout: UVLayout, source_vertices: np.ndarray,
         source_faces: np.ndarray, texture: SurfaceTexture) -> np.ndarray:
    """The input's base colour on the result's UV layout.

    Parameters
    ----------
    vertices : (V, 3) float, faces : (F, 3) int
        The result, in the input's frame.
    layout : UVLayout
        The result's layout; the texture has ``layout.size`` texels a side.
    source_vertices : (N, 3) float, source_faces : (M, 3) int
        The input mesh, with ``texture`` at its vertices.

    Returns
    -------
    (S, S, 4) uint8 RGBA image, the first row the top (S = ``layout.size``).
    """
    from scipy.ndimage import distance_transform_edt

    size = layout.size
    face, texel, bary = rasterize(layout.uv, layout.faces, size)
    corners = np.asarray(vertices, dtype=np.float64)[np.asarray(faces, dtype=np.int64)[face]]  # (N, 3, 3)
    points = np.einsum("nk,nkd->nd", bary, corners)
    src_faces = np.asarray(source_faces, dtype=np.int64)
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces, dtype=np.int64)]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
    texel_size = np.sqrt(area / max(len(texel), 1))  # metres a texel covers
    hit, hit_bary = nearest_points(points, source_vertices, src_faces, spacing=2 * texel_size)
    corner_uv = texture.uv[src_faces[hit]]  # (N, 3, 2)
    uv = np.einsum("nk,nkd->nd", hit_bary, corner_uv)
    owner = texture.image_of[src_faces[hit, 0]]
    colour = np.full((len(points), 4), 255.0)  # untextured input: glTF's default white
    for k, image in enumerate(texture.images):
        sel = (owner == k) & np.all(np.isfinite(uv), axis=1)
        colour[sel] = sample(image, uv[sel]) * texture.factors[k]
    out = np.zeros((size * size, 4))
    out[texel] = colour
    filled = np.zeros(size * size, dtype=bool)
    filled[texel] = True
    if not filled.any():
        return np.full((size, size, 4), 255, dtype=np.uint8)
    # Every other texel takes its nearest filled texel's colour.
    idx = distance_transform_edt(~filled.reshape(size, size), return_distances=False, return_indices=True)
    out = out.reshape(size, size, 4)[idx[0], idx[1]]
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)
