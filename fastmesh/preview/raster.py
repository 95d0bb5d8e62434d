"""The rasteriser of :mod:`.render`: how a preview looks (:class:`RenderConfig`), the camera fitted to a shape,
and triangles and point splats turned into fragments kept by a per-pixel depth test."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..shapes.shape import ShapeError

EMPTY = np.iinfo(np.int64).max  # z-buffer value of a pixel no fragment reached
_DEPTH_LEVELS = (1 << 31) - 1  # depth quantisation: fits above a 32-bit id in a positive int64
# Padded bounding-box sizes for batching triangles (ratio ~1.25, so padding wastes < ~1.5x area).
_BOX_EDGES = np.unique(np.round(1.25 ** np.arange(0, 48)).astype(np.int64))


@dataclass(frozen=True)
class RenderConfig:
    """Everything that decides how a preview looks.  Colours are RGB in [0, 1]."""

    azimuth_deg: float = 35.0  # camera around the up axis, from the +front axis towards +x
    elevation_deg: float = 25.0  # camera above the horizon
    up: str = "y"  # world up axis: "y" (glTF/three.js, OBJ) or "z" (Quake-family game assets)
    fov_deg: float = 30.0  # mild perspective; the framing then zooms to fit anyway
    margin: float = 0.05  # empty border around the shape, fraction of the image side
    supersample: int = 2  # render at k x size and box-filter down (anti-aliasing)
    background: tuple[float, float, float] = (0.965, 0.968, 0.975)
    face_color: tuple[float, float, float] = (0.72, 0.78, 0.88)
    # Lights are fixed in camera space, so every preview is lit the same way whatever the shape.
    # The key light sits near the view axis (faces turned to the viewer read brightest, as in a
    # modelling tool), a little up and left so the top and the right side read as different planes.
    key_light: tuple[float, float, float] = (-0.3, 0.45, 0.85)
    fill_light: tuple[float, float, float] = (0.7, -0.25, 0.4)  # lower right, weak: no pitch-black faces
    ambient: float = 0.24
    key_strength: float = 0.72
    fill_strength: float = 0.2
    wire_color: tuple[float, float, float] = (0.10, 0.12, 0.16)
    wire_opacity: float = 0.85
    wire_width: float = 1.0  # output pixels
    outline_opacity: float = 0.5  # silhouette darkening, one working pixel wide (0 = off)
    point_color: tuple[float, float, float] = (0.90, 0.42, 0.16)  # overlay points on a mesh
    cloud_color: tuple[float, float, float] = (0.60, 0.72, 0.90)  # render_points
    overlay_point_radius: float = 1.3  # output pixels
    # render_points picks a splat radius that roughly closes the surface: k * size / sqrt(N).
    cloud_radius_scale: float = 1.2
    cloud_radius_range: tuple[float, float] = (0.8, 4.0)
    # Overlay points lie on the surface they are drawn over; pulling them this fraction of the
    # scene's depth range towards the camera stops them z-fighting with it.
    point_depth_bias: float = 0.01
    max_points: int = 200_000  # larger clouds are evenly subsampled (preview, not archive)
    batch_pixels: int = 1 << 20  # candidate pixels per numpy batch (memory ~ 40 B each)
    face_batch: int = 1 << 18  # faces set up per batch (memory ~ 400 B each)
    min_size: int = 16
    max_size: int = 2048
    # Supersampling is reduced so the working image stays <= this side (memory ~ 24 B per pixel).
    max_working_side: int = 2048


DEFAULT_CONFIG = RenderConfig()


# --------------------------------------------------------------------------- camera


@dataclass(frozen=True)
class Camera:
    """Perspective camera.  ``rotation`` rows are the view axes (right, up, towards viewer)."""

    eye: np.ndarray  # (3,) world position
    rotation: np.ndarray  # (3, 3) world -> view
    focal: float  # pixels per unit of x/z
    center: tuple[float, float]  # principal point (col, row), pixels
    size: int  # image side, pixels

    def project(self, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(N, 3) world points -> screen ``x`` (col), ``y`` (row), inverse depth ``1/z``."""
        rel = (np.asarray(v, dtype=np.float64) - self.eye) @ self.rotation.T
        iz = 1.0 / -rel[:, 2]
        return self.center[0] + self.focal * rel[:, 0] * iz, self.center[1] - self.focal * rel[:, 1] * iz, iz


def view_direction(cfg: RenderConfig = DEFAULT_CONFIG) -> np.ndarray:
    """Unit vector from the shape's centre towards the camera, world coordinates."""
    az, el = np.radians(cfg.azimuth_deg), np.radians(cfg.elevation_deg)
    right, up, front = np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)
    if cfg.up == "y":  # front = +z
        return np.array([right, up, front])
    if cfg.up == "z":  # front = -y (Quake-style models face +x; -y shows their left 3/4)
        return np.array([right, -front, up])
    raise ValueError(f"up must be 'y' or 'z', got {cfg.up!r}")


def fit_camera(points: np.ndarray, size: int, cfg: RenderConfig = DEFAULT_CONFIG) -> Camera:
    """Camera looking along the fixed 3/4 direction whose image of ``points`` fills ``size``.

    The eye is placed outside the bounding sphere (nothing is behind or at the camera),
    then focal length and principal point are chosen so the projected extent spans the
    image minus ``margin`` on its longer side, centred.
    """
    lo, hi = points.min(0), points.max(0)
    centre, radius = (lo + hi) / 2, float(np.linalg.norm(hi - lo)) / 2
    if not radius > 0:
        raise ShapeError("degenerate", "shape has zero extent (all points coincide)")
    d = view_direction(cfg)
    world_up = np.array([0.0, 1.0, 0.0]) if cfg.up == "y" else np.array([0.0, 0.0, 1.0])
    right = np.cross(world_up, d)
    right /= np.linalg.norm(right)
    rot = np.stack([right, np.cross(d, right), d])
    eye = centre + d * radius / np.sin(np.radians(cfg.fov_deg) / 2)
    unit = Camera(eye=eye, rotation=rot, focal=1.0, center=(0.0, 0.0), size=size)
    u, v, _ = unit.project(points)
    v = -v  # unit camera rows are -y/z; undo to get y/z
    extent = max(u.max() - u.min(), v.max() - v.min())
    if not extent > 1e-12 * radius:
        raise ShapeError("degenerate", "shape projects to a single point")
    focal = size * (1 - 2 * cfg.margin) / extent
    cx = size / 2 - focal * (u.max() + u.min()) / 2
    cy = size / 2 + focal * (v.max() + v.min()) / 2
    return Camera(eye=eye, rotation=rot, focal=focal, center=(cx, cy), size=size)


# --------------------------------------------------------------------------- rasterisation


def barycentric_planes(x: np.ndarray, y: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per face, the affine maps pixel -> barycentric coordinate.

    Returns ``planes`` (F, 3, 3): ``b_i = A*x + B*y + C`` with ``planes[f, i] = (A, B, C)``,
    and twice the signed screen area (F,).  Dividing by the signed area makes both
    windings come out positive inside.
    """
    px, py = x[faces], y[faces]  # (F, 3)
    j, k = [1, 2, 0], [2, 0, 1]
    area2 = (px[:, 1] - px[:, 0]) * (py[:, 2] - py[:, 0]) - (px[:, 2] - px[:, 0]) * (py[:, 1] - py[:, 0])
    safe = np.where(area2 == 0, 1.0, area2)[:, None]
    a = (py[:, j] - py[:, k]) / safe
    b = (px[:, k] - px[:, j]) / safe
    c = (px[:, j] * py[:, k] - px[:, k] * py[:, j]) / safe
    return np.stack([a, b, c], axis=2), area2


def raster_triangles(x, y, depth, faces, zbuf: np.ndarray, side: int, cfg: RenderConfig,
                      id_offset: int = 0) -> None:
    """Depth-test every pixel centre covered by a triangle into ``zbuf`` (ids = id_offset + face index).

    ``depth`` (N,) is per vertex, normalised to [0, 1] and linear in screen space.
    """
    planes, area2 = barycentric_planes(x, y, faces)
    fx, fy = x[faces], y[faces]
    # Pixel centres inside the bounding box: col + 0.5 in [min x, max x].
    x0 = np.maximum(np.ceil(fx.min(1) - 0.5), 0).astype(np.int64)
    x1 = np.minimum(np.floor(fx.max(1) - 0.5), side - 1).astype(np.int64)
    y0 = np.maximum(np.ceil(fy.min(1) - 0.5), 0).astype(np.int64)
    y1 = np.minimum(np.floor(fy.max(1) - 0.5), side - 1).astype(np.int64)
    # Edge-on and sub-pixel triangles that contain no pixel centre contribute nothing.
    live = np.flatnonzero((x1 >= x0) & (y1 >= y0) & (np.abs(area2) > 1e-12))
    if len(live) == 0:
        return
    w, h = x1[live] - x0[live] + 1, y1[live] - y0[live] + 1
    # Re-base each plane at its box's first pixel centre: local coordinates are small
    # integers, so float32 evaluation stays exact enough for the inside test.
    ox, oy = x0[live] + 0.5, y0[live] + 0.5
    pl = planes[live]
    pl[:, :, 2] += pl[:, :, 0] * ox[:, None] + pl[:, :, 1] * oy[:, None]
    dz = np.einsum("fi,fij->fj", depth[faces[live]], pl)  # depth plane (F, 3)
    coef = np.concatenate([pl.reshape(-1, 9), dz], axis=1).astype(np.float32)  # (F, 12)

    bw = np.searchsorted(_BOX_EDGES, w)
    bh = np.searchsorted(_BOX_EDGES, h)
    group = bw * len(_BOX_EDGES) + bh
    order = np.argsort(group, kind="stable")
    starts = np.flatnonzero(np.r_[True, np.diff(group[order]) != 0])
    ends = np.r_[starts[1:], len(order)]
    tol = np.float32(-1e-5)  # shared edges: rather a duplicate fragment (z resolves it) than a crack
    for s, e in zip(starts, ends, strict=True):
        W, H = int(_BOX_EDGES[bw[order[s]]]), int(_BOX_EDGES[bh[order[s]]])
        step = max(1, cfg.batch_pixels // (W * H))
        lx = np.arange(W, dtype=np.float32)[None, None, :]
        ly = np.arange(H, dtype=np.float32)[None, :, None]
        for cs in range(s, e, step):
            sel = order[cs:min(cs + step, e)]
            c = coef[sel][:, :, None, None]  # (T, 12, 1, 1)
            inside = (lx < w[sel, None, None]) & (ly < h[sel, None, None])
            for i in range(3):
                inside &= c[:, 3 * i] * lx + c[:, 3 * i + 1] * ly + c[:, 3 * i + 2] >= tol
            t, yy, xx = np.nonzero(inside)
            if len(t) == 0:
                continue
            dz_t = c[t, 9:12, 0, 0]
            d = dz_t[:, 0] * xx + dz_t[:, 1] * yy + dz_t[:, 2]
            f = sel[t]
            pix = (y0[live[f]] + yy) * side + x0[live[f]] + xx
            _depth_test(zbuf, pix, d, live[f] + id_offset)


def raster_splats(x, y, depth, radius: float, zbuf: np.ndarray, side: int, id_offset: int) -> None:
    """Discs of ``radius`` pixels at constant depth, ids ``id_offset + point index``."""
    r = int(np.ceil(radius))
    off = np.arange(-r, r + 1)
    oy, ox = np.meshgrid(off, off, indexing="ij")
    keep = (ox**2 + oy**2) <= (radius + 0.5) ** 2  # disc, a little generous so r<1 still hits a pixel
    ox, oy = ox[keep], oy[keep]
    cx, cy = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    step = max(1, (1 << 20) // len(ox))
    for s in range(0, len(x), step):
        px = cx[s:s + step, None] + ox[None]
        py = cy[s:s + step, None] + oy[None]
        ok = (px >= 0) & (px < side) & (py >= 0) & (py < side)
        i, k = np.nonzero(ok)
        pid = s + i
        _depth_test(zbuf, py[i, k] * side + px[i, k], depth[pid], pid + id_offset)


def _depth_test(zbuf: np.ndarray, pix: np.ndarray, depth: np.ndarray, ids: np.ndarray) -> None:
    """Keep, per pixel, the nearest fragment; ties go to the smaller id (order-independent)."""
    q = (np.clip(depth, 0.0, 1.0) * _DEPTH_LEVELS).astype(np.int64)
    np.minimum.at(zbuf, pix, (q << 32) | ids.astype(np.int64))
