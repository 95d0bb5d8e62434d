"""Headless CPU preview renderer: meshes and point clouds to RGB(A) images and PNG bytes.

No GL, no display, numpy only.  The pipeline is a classic deferred rasteriser:

1. A fixed 3/4-view perspective camera is fitted so the shape's projection fills the
   image (:func:`fit_camera`).
2. Every triangle (and every point splat) emits *fragments* ``(pixel, depth, id)``.
   Triangles are rasterised in batches of equal padded bounding-box size, so the
   per-pixel edge tests are numpy broadcasts instead of Python loops.
3. A per-pixel z-buffer keeps the nearest fragment: depth and id are packed into one
   int64 ``(depth << 32) | id`` and reduced with ``np.minimum.at`` - a real depth test
   per pixel, independent of the order faces come in (no painter's sorting).
4. The winning id per pixel is shaded (flat, two-sided Lambert; artist meshes have
   inconsistent winding), the wireframe is drawn from the winning face's screen-space
   barycentrics (so only edges of *visible* faces appear), and the image is rendered at
   ``supersample`` times the size and box-filtered down for anti-aliasing.

Steps 1-3 (the look, the camera, the rasteriser) are :mod:`.raster`; this module checks the inputs, shades and
composes the picture.

Conventions: pixel ``(row, col)`` covers ``[col, col+1) x [row, row+1)`` in screen units,
rows grow downwards, its centre is at ``+0.5``.  Depth is carried as inverse view depth
``1/z``, which is exactly linear in screen space, then normalised to [0, 1] (0 = nearest).
"""

from __future__ import annotations

import numpy as np

from fastmesh.preview.png import to_png  # re-exported: render + encode in one import
from fastmesh.shapes.shape import ShapeError

from .raster import (
    DEFAULT_CONFIG,
    EMPTY,
    Camera,
    RenderConfig,
    barycentric_planes,
    fit_camera,
    raster_splats,
    raster_triangles,
    view_direction,
)

# --------------------------------------------------------------------------- validation


def _as_points(a, name: str, allow_empty: bool = False) -> np.ndarray:
    try:
        arr = np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError):
        raise ShapeError("unreadable", f"{name} must be a numeric (N, 3) array") from None
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ShapeError("unreadable", f"{name} must have shape (N, 3), got {arr.shape}")
    if len(arr) == 0 and not allow_empty:
        raise ShapeError("empty", f"{name} is empty: nothing to render")
    if not np.isfinite(arr).all():
        raise ShapeError("non_finite", f"{name} contain NaN or infinity")
    return arr


def _as_faces(f, n_vertices: int) -> np.ndarray:
    try:
        arr = np.asarray(f)
    except (TypeError, ValueError):
        raise ShapeError("unreadable", "faces must be an integer (F, 3) array") from None
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ShapeError("unreadable", f"faces must have shape (F, 3), got {arr.shape}")
    if len(arr) == 0:
        raise ShapeError("empty", "mesh has no faces: nothing to render")
    if arr.dtype.kind not in "iu":
        if arr.dtype.kind != "f" or not np.isfinite(arr).all() or (arr != np.round(arr)).any():
            raise ShapeError("unreadable", "face indices must be integers")
    arr = arr.astype(np.int64)
    if arr.min() < 0 or arr.max() >= n_vertices:
        raise ShapeError("unreadable", f"face indices must lie in [0, {n_vertices - 1}]")
    return arr


def _check_size(size, cfg: RenderConfig) -> int:
    if isinstance(size, bool) or not isinstance(size, (int, np.integer)):
        raise ValueError(f"size must be an integer, got {size!r}")
    if not cfg.min_size <= size <= cfg.max_size:
        raise ValueError(f"size must be between {cfg.min_size} and {cfg.max_size} pixels, got {size}")
    return int(size)


# --------------------------------------------------------------------------- shading


def _lambert(normals_view: np.ndarray, cfg: RenderConfig) -> np.ndarray:
    """Two-sided Lambert intensity of (N, 3) camera-facing unit normals in view space."""
    key = np.asarray(cfg.key_light, dtype=np.float64)
    fill = np.asarray(cfg.fill_light, dtype=np.float64)
    key, fill = key / np.linalg.norm(key), fill / np.linalg.norm(fill)
    return (cfg.ambient + cfg.key_strength * np.clip(normals_view @ key, 0, None)
            + cfg.fill_strength * np.clip(normals_view @ fill, 0, None))


def _face_shades(v: np.ndarray, faces: np.ndarray, cam: Camera, cfg: RenderConfig,
                 back_color: tuple[float, float, float] | None = None) -> np.ndarray:
    """(F, 3) flat colours: face normals turned towards the eye, then lit; faces seen from their back in
    ``back_color`` where given."""
    tri = v[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    towards_eye = cam.eye - tri.mean(1)
    back = (n * towards_eye).sum(1) < 0
    n *= np.where(back, -1.0, 1.0)[:, None]  # two-sided lighting
    color = np.tile(np.asarray(cfg.face_color, dtype=np.float64), (len(faces), 1))
    if back_color is not None:
        color[back] = back_color
    return _lambert(n @ cam.rotation.T, cfg)[:, None] * color


def _normalised_depth(iz: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Inverse depth -> [0, 1], 0 nearest; affine, so it stays linear in screen space."""
    return (hi - iz) / max(hi - lo, 1e-12 * hi)


def _compose(zbuf: np.ndarray, colors: np.ndarray, side: int, cfg: RenderConfig,
             wire=None) -> tuple[np.ndarray, np.ndarray]:
    """Winning ids -> float RGB image and coverage, both (side, side[, 3]) float32."""
    idx = np.flatnonzero(zbuf != EMPTY)
    ids = (zbuf[idx] & 0xFFFFFFFF).astype(np.int64)
    rgb = colors[ids]
    if wire is not None:
        a = wire(idx, ids)[:, None]
        rgb += (np.asarray(cfg.wire_color, dtype=np.float32) - rgb) * a
    img = np.empty((side * side, 3), dtype=np.float32)
    img[:] = cfg.background
    img[idx] = rgb
    cov = np.zeros(side * side, dtype=np.float32)
    cov[idx] = 1.0
    img, cov = img.reshape(side, side, 3), cov.reshape(side, side)
    if cfg.outline_opacity > 0:
        # Covered pixels next to an empty one form the silhouette; darkening them a little keeps
        # light top faces from melting into the light background.
        edge = np.zeros((side, side), dtype=bool)
        inside = cov > 0
        edge[1:] |= inside[1:] & ~inside[:-1]
        edge[:-1] |= inside[:-1] & ~inside[1:]
        edge[:, 1:] |= inside[:, 1:] & ~inside[:, :-1]
        edge[:, :-1] |= inside[:, :-1] & ~inside[:, 1:]
        img[edge] += (np.asarray(cfg.wire_color, dtype=np.float32) - img[edge]) * np.float32(cfg.outline_opacity)
    return img, cov


def _wire_alpha(x, y, faces, n_faces: int, side: int, width: float, cfg: RenderConfig):
    """A function (pixel indices, winning ids) -> wireframe opacity for those pixels.

    The distance of a pixel centre to the nearest edge of its *visible* face, in pixels,
    is b_i / |grad b_i| (screen-space barycentrics), so an edge shows exactly where a face
    it bounds is visible: occlusion comes from the z-buffer itself, no depth bias to tune.
    The line is anti-aliased by a one-pixel ramp; each face draws half its width, the
    neighbour across the edge the other half.
    """
    # Scale each plane by 1/|grad b_i| once per face: then |plane(pixel)| is the distance itself.
    dist_planes = np.empty((len(faces), 9), dtype=np.float32)
    for s in range(0, len(faces), cfg.face_batch):
        planes, _ = barycentric_planes(x, y, faces[s:s + cfg.face_batch])
        grad = np.maximum(np.hypot(planes[:, :, 0], planes[:, :, 1]), 1e-12)
        dist_planes[s:s + len(planes)] = (planes / grad[:, :, None]).reshape(-1, 9)
    ramp = np.float32(width / 2 + 0.5)

    def alpha(idx: np.ndarray, ids: np.ndarray) -> np.ndarray:
        out = np.zeros(len(idx), dtype=np.float32)
        is_face = ids < n_faces
        pl = dist_planes[ids[is_face]]  # (K, 9)
        px = (idx[is_face] % side).astype(np.float32) + np.float32(0.5)
        py = (idx[is_face] // side).astype(np.float32) + np.float32(0.5)
        dist = np.abs(pl[:, 0] * px + pl[:, 1] * py + pl[:, 2])
        for i in (1, 2):
            np.minimum(dist, np.abs(pl[:, 3 * i] * px + pl[:, 3 * i + 1] * py + pl[:, 3 * i + 2]), out=dist)
        out[is_face] = np.clip(ramp - dist, 0, 1) * np.float32(cfg.wire_opacity)
        return out

    return alpha


def _finish(img: np.ndarray, cov: np.ndarray, ss: int, alpha: bool) -> np.ndarray:
    """Box-filter the supersampled image down and quantise to uint8."""
    if ss > 1:  # strided sums: much faster than reshape(...).mean(axis=(1, 3))
        img = sum(img[i::ss, j::ss] for i in range(ss) for j in range(ss)) / np.float32(ss * ss)
        cov = sum(cov[i::ss, j::ss] for i in range(ss) for j in range(ss)) / np.float32(ss * ss)
    if alpha:
        img = np.concatenate([img, cov[:, :, None]], axis=2)
    return np.clip(np.rint(img * 255), 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------- public API


def render_mesh(vertices, faces, size: int = 512, wireframe: bool = False, points=None,
                alpha: bool = False, config: RenderConfig = DEFAULT_CONFIG,
                back_color: tuple[float, float, float] | None = None) -> np.ndarray:
    """Render a triangle mesh from the fixed 3/4 view.

    Parameters
    ----------
    vertices : (N, 3) float
        Positions, any units (the camera frames them).
    faces : (F, 3) int
        Triangles; winding may be inconsistent (lighting is two-sided).
    size : int
        Image side in pixels.
    wireframe : bool
        Overlay the edges of the visible faces.
    points : (M, 3) float, optional
        Points drawn as small depth-tested splats on top (e.g. the input point cloud).
    alpha : bool
        Return RGBA with the background transparent (coverage as alpha).
    config : RenderConfig
    back_color : (3,) float in [0, 1], optional
        Colour of the faces seen from their back (their winding turns them away from the camera);
        without it both sides look alike.

    Returns
    -------
    (size, size, 3) or (size, size, 4) uint8

    Raises
    ------
    ShapeError (a ValueError)
        No vertices or faces, NaN/inf, out-of-range indices, zero extent.
    """
    size = _check_size(size, config)
    v, f, pts, referenced = _mesh_inputs(vertices, faces, points, config)
    ss = _supersample(size, config)
    side = size * ss
    # Unreferenced vertices must not shrink the framing or the depth range.
    cam = fit_camera(v[referenced] if pts is None else np.concatenate([v[referenced], pts]), side, config)
    x, y, iz = cam.project(v)
    lo, hi = iz[referenced].min(), iz[referenced].max()
    if pts is not None:
        px, py, piz = cam.project(pts)
        lo, hi = min(lo, piz.min()), max(hi, piz.max())
    zbuf = np.full(side * side, EMPTY, dtype=np.int64)
    colors = _raster_mesh(v, f, (x, y, _normalised_depth(iz, lo, hi)), cam, zbuf, side, config, back_color)
    if pts is not None:  # splats drawn over the faces, slightly nearer (``point_depth_bias``)
        depth = _normalised_depth(piz, lo, hi) - config.point_depth_bias
        raster_splats(px, py, depth, config.overlay_point_radius * ss, zbuf, side, id_offset=len(f))
        colors = np.concatenate([colors, np.tile(np.asarray(config.point_color, dtype=np.float32), (len(pts), 1))])
    wire = _wire_alpha(x, y, f, len(f), side, config.wire_width * ss, config) if wireframe else None
    img, cov = _compose(zbuf, colors, side, config, wire)
    return _finish(img, cov, ss, alpha)


def _mesh_inputs(vertices, faces, points, config: RenderConfig
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]:
    """:func:`render_mesh`'s inputs checked: vertices (N, 3), faces (F, 3), the overlay points subsampled
    (``max_points``; None where there are none) and the (N,) mask of the vertices the faces use."""
    v = _as_points(vertices, "vertices")
    f = _as_faces(faces, len(v))
    pts = None if points is None else _subsample(_as_points(points, "points", allow_empty=True), config)
    referenced = np.zeros(len(v), dtype=bool)
    referenced[f.ravel()] = True
    return v, f, pts if pts is not None and len(pts) else None, referenced


def _raster_mesh(v: np.ndarray, f: np.ndarray, screen: tuple[np.ndarray, np.ndarray, np.ndarray], cam: Camera,
                 zbuf: np.ndarray, side: int, config: RenderConfig,
                 back_color: tuple[float, float, float] | None) -> np.ndarray:
    """Rasterise faces ``f`` into ``zbuf`` (their ids from 0) at the vertices' ``screen`` x, y and normalised
    depth, and return their (F, 3) float32 shades."""
    x, y, depth = screen
    colors = np.empty((len(f), 3), dtype=np.float32)
    for s in range(0, len(f), config.face_batch):  # bounded memory for dense (input) meshes
        chunk = f[s:s + config.face_batch]
        raster_triangles(x, y, depth, chunk, zbuf, side, config, id_offset=s)
        colors[s:s + len(chunk)] = _face_shades(v, chunk, cam, config, back_color)
    return colors


def render_points(points, normals=None, size: int = 512, alpha: bool = False,
                  config: RenderConfig = DEFAULT_CONFIG) -> np.ndarray:
    """Render a point cloud as depth-tested round splats from the fixed 3/4 view.

    Parameters
    ----------
    points : (N, 3) float
    normals : (N, 3) float, optional
        Per-point normals for two-sided Lambert shading; without them, splats are shaded
        by depth (nearer is lighter) so the shape still reads as 3D.
    size : int
        Image side in pixels.
    alpha : bool
        Return RGBA with the background transparent.
    config : RenderConfig

    Returns
    -------
    (size, size, 3) or (size, size, 4) uint8
    """
    size = _check_size(size, config)
    p = _as_points(points, "points")
    n = None if normals is None else _as_points(normals, "normals")
    if n is not None and n.shape != p.shape:
        raise ShapeError("unreadable", f"normals must match points: {n.shape} vs {p.shape}")
    keep = _subsample_index(len(p), config)
    p = p[keep]
    n = None if n is None else n[keep]
    ss = _supersample(size, config)
    side = size * ss
    cam = fit_camera(p, side, config)
    x, y, iz = cam.project(p)
    depth = _normalised_depth(iz, iz.min(), iz.max())
    lo_r, hi_r = config.cloud_radius_range
    radius = float(np.clip(config.cloud_radius_scale * size / np.sqrt(len(p)), lo_r, hi_r)) * ss
    zbuf = np.full(side * side, EMPTY, dtype=np.int64)
    raster_splats(x, y, depth, radius, zbuf, side, id_offset=0)
    if n is not None:
        n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
        n *= np.where((n * (cam.eye - p)).sum(1) < 0, -1.0, 1.0)[:, None]
        shade = _lambert(n @ cam.rotation.T, config)
    else:
        shade = 1.0 - 0.55 * depth  # depth cue only
    colors = (shade[:, None] * np.asarray(config.cloud_color)).astype(np.float32)
    img, cov = _compose(zbuf, colors, side, config, None)
    return _finish(img, cov, ss, alpha)


def render_shape(shape, size: int = 512, wireframe: bool = False, alpha: bool = False,
                 config: RenderConfig = DEFAULT_CONFIG) -> np.ndarray:
    """Render a :class:`fastmesh.shapes.shape.Shape`: a mesh with :func:`render_mesh`, points with
    :func:`render_points`."""
    if shape.faces is not None:
        return render_mesh(shape.vertices, shape.faces, size=size, wireframe=wireframe, alpha=alpha, config=config)
    return render_points(shape.vertices, shape.normals, size=size, alpha=alpha, config=config)


def _supersample(size: int, cfg: RenderConfig) -> int:
    return max(1, min(int(cfg.supersample), cfg.max_working_side // size))


def _subsample_index(n: int, cfg: RenderConfig) -> np.ndarray:
    """Evenly spaced indices, at most ``max_points`` (deterministic: same input, same picture)."""
    if n <= cfg.max_points:
        return np.arange(n)
    return np.linspace(0, n - 1, cfg.max_points).astype(np.int64)


def _subsample(p: np.ndarray, cfg: RenderConfig) -> np.ndarray:
    return p[_subsample_index(len(p), cfg)]


__all__ = ["RenderConfig", "DEFAULT_CONFIG", "Camera", "fit_camera", "view_direction", "render_mesh",
           "render_points", "render_shape", "to_png"]
