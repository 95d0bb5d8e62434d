"""What a renderer shows of a mesh: back faces seen, silhouette and shading normals against a reference.

../shared/EVAL.md, "What a renderer shows".  A mesh is drawn with an ordinary z-buffer
(:func:`fastmesh.preview.raster.raster_triangles`) from the 14 directions of :data:`VIEWS` (the four
sides, eight at 45 degrees above and below the horizon between them, top and bottom), every camera fitted
to one box (the reference's), so that a result and its reference are seen through the same cameras:

    back_face_share   of the pixels a mesh covers, the share where the nearest face is seen from its back
                      (its winding turns it away from the camera), pooled over the views, 0..1
    silhouette_iou    per view, covered pixels of both / covered pixels of either; mean over the views
    normal_angle      on pixels both cover, the angle between the two nearest faces' normals, each turned
                      towards the camera, in degrees; mean over those pixels

A face seen from its back is exact per face and view: ``n . (eye - p)`` is the same for every point ``p`` of
the face's plane.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..preview.raster import DEFAULT_CONFIG, EMPTY, Camera, raster_triangles

VIEW_SIZE = 160  # image side of each view, pixels: ~25k pixels a view, enough for a 1 % share
VIEW_FOV = 30.0  # degrees; the preview's mild perspective
MARGIN = 0.05  # empty border around the box, fraction of the image side
BACK_BIAS = 1e-6  # of the depth range: a back face at the same depth as a front face is behind it


def _views() -> np.ndarray:
    """(14, 3) unit directions from the shape's centre towards the cameras, y up."""
    dirs = [(np.sin(a), 0.0, np.cos(a)) for a in np.radians([0, 90, 180, 270])]
    for el in (45.0, -45.0):
        e = np.radians(el)
        dirs += [(np.cos(e) * np.sin(a), np.sin(e), np.cos(e) * np.cos(a)) for a in np.radians([45, 135, 225, 315])]
    dirs += [(0.0, 1.0, 0.0), (0.0, -1.0, 0.0)]
    return np.asarray(dirs, dtype=np.float64)


VIEWS = _views()


def cameras(points: np.ndarray, size: int = VIEW_SIZE, directions: np.ndarray = VIEWS) -> list[Camera]:
    """One perspective camera per direction, each framing the axis-aligned box of ``points``.

    Parameters
    ----------
    points : (N, 3) float, N >= 1, the points whose box every camera frames (the reference's vertices)
    size : int, image side in pixels
    directions : (K, 3) float, from the box's centre towards each camera

    Returns
    -------
    list of K :class:`fastmesh.preview.raster.Camera`
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    lo, hi = p.min(0), p.max(0)
    centre, radius = (lo + hi) / 2, max(float(np.linalg.norm(hi - lo)) / 2, 1e-12)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    out = []
    for d in np.asarray(directions, dtype=np.float64):
        d = d / np.linalg.norm(d)
        hint = np.array([0.0, 1.0, 0.0]) if abs(d[1]) < 0.99 else np.array([0.0, 0.0, -np.sign(d[1])])
        right = np.cross(hint, d)
        right /= np.linalg.norm(right)
        rot = np.stack([right, np.cross(d, right), d])
        eye = centre + d * radius / np.sin(np.radians(VIEW_FOV) / 2)
        rel = (corners - eye) @ rot.T
        u, v = rel[:, 0] / -rel[:, 2], rel[:, 1] / -rel[:, 2]
        extent = max(np.ptp(u), np.ptp(v), 1e-12)
        focal = size * (1 - 2 * MARGIN) / extent
        centre_px = (size / 2 - focal * (u.max() + u.min()) / 2, size / 2 + focal * (v.max() + v.min()) / 2)
        out.append(Camera(eye=eye, rotation=rot, focal=focal, center=centre_px, size=size))
    return out


def face_ids(vertices: np.ndarray, faces: np.ndarray, cam: Camera) -> np.ndarray:
    """(size * size,) int64 the nearest face at each pixel centre (row-major), -1 where none.

    Faces with a corner at or behind the eye are left out (a camera fitted to another shape's box can sit
    inside a result that overshoots it).  A face seen from its back lies ``BACK_BIAS`` of the depth range
    further away than it is: where a front and a back face are at the same depth (along a silhouette edge,
    or a sheet doubled to show both sides) the front one is seen.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    side = cam.size
    zbuf = np.full(side * side, EMPTY, dtype=np.int64)
    x, y, iz = cam.project(v)
    fx, fy = x[f], y[f]
    # In front of the eye, and holding a pixel centre (the rasteriser's own test, done first here because
    # most faces of a dense mesh hold none at this size and setting them up costs more than this test).
    front = np.flatnonzero((iz[f] > 0).all(1)
                           & (np.ceil(fx.min(1) - 0.5) <= np.floor(fx.max(1) - 0.5))
                           & (np.ceil(fy.min(1) - 0.5) <= np.floor(fy.max(1) - 0.5)))
    if len(front):
        g = f[front]
        tri = v[g]
        back = np.einsum("fd,fd->f", np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), cam.eye - tri[:, 0]) < 0
        lo, hi = iz[g].min(), iz[g].max()
        depth = (hi - iz[g]) / max(hi - lo, 1e-12 * hi) + np.where(back, BACK_BIAS, 0.0)[:, None]  # (F', 3)
        corners = np.arange(3 * len(g)).reshape(-1, 3)  # each face with its own corners, for its own depth
        for s in range(0, len(g), DEFAULT_CONFIG.face_batch):
            raster_triangles(x[g].ravel(), y[g].ravel(), depth.ravel(), corners[s:s + DEFAULT_CONFIG.face_batch],
                             zbuf, side, DEFAULT_CONFIG, id_offset=s)
    ids = np.full(side * side, -1, dtype=np.int64)
    hit = zbuf != EMPTY
    ids[hit] = front[zbuf[hit] & 0xFFFFFFFF]
    return ids


@dataclass(frozen=True)
class Views:
    """A mesh seen through a list of cameras: per view ``ids`` (P,) nearest face or -1, ``back`` (P,) bool
    the pixel shows a face's back, ``normals`` (P, 3) float32 unit normal of that face turned towards the
    camera (zero where nothing is seen)."""

    ids: list[np.ndarray]
    back: list[np.ndarray]
    normals: list[np.ndarray]


def render_views(vertices: np.ndarray, faces: np.ndarray, cams: list[Camera]) -> Views:
    """Rasterise (V, 3) ``vertices`` / (F, 3) ``faces`` through every camera of ``cams`` (:func:`cameras`)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    tri = v[f]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    ids, back, normals = [], [], []
    for cam in cams:
        i = face_ids(v, f, cam)
        facing = np.einsum("fd,fd->f", n, cam.eye - tri[:, 0]) >= 0  # (F,) front side towards this camera
        seen = i >= 0
        b = np.zeros(len(i), dtype=bool)
        b[seen] = ~facing[i[seen]]
        nv = np.zeros((len(i), 3), dtype=np.float32)
        nv[seen] = n[i[seen]] * np.where(b[seen], -1.0, 1.0)[:, None]
        ids.append(i)
        back.append(b)
        normals.append(nv)
    return Views(ids, back, normals)


def back_face_share(views: Views) -> float:
    """Back-facing pixels / covered pixels over all views (0 where nothing is covered)."""
    covered = sum(int((i >= 0).sum()) for i in views.ids)
    return sum(int(b.sum()) for b in views.back) / covered if covered else 0.0


def silhouette_iou(a: Views, b: Views) -> float:
    """Mean over the views of covered-by-both / covered-by-either (1 where neither covers anything)."""
    out = []
    for ia, ib in zip(a.ids, b.ids, strict=True):
        union = int(((ia >= 0) | (ib >= 0)).sum())
        out.append(int(((ia >= 0) & (ib >= 0)).sum()) / union if union else 1.0)
    return float(np.mean(out))


def normal_angle(a: Views, b: Views) -> float:
    """Mean angle in degrees between camera-facing normals on pixels both cover (nan where none)."""
    total, count = 0.0, 0
    for ia, ib, na, nb in zip(a.ids, b.ids, a.normals, b.normals, strict=True):
        both = (ia >= 0) & (ib >= 0)
        a, b = na[both].astype(np.float64), nb[both].astype(np.float64)
        # atan2 of sine and cosine: arccos loses its precision near 0 degrees
        angle = np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.einsum("pd,pd->p", a, b))
        total += float(np.degrees(angle).sum())
        count += int(both.sum())
    return total / count if count else float("nan")


def visible_report(vertices: np.ndarray, faces: np.ndarray, reference: tuple[np.ndarray, np.ndarray] | None = None,
                   box: np.ndarray | None = None, size: int = VIEW_SIZE,
                   reference_views: Views | None = None) -> dict:
    """What the 14 views show of a mesh, alone or against a reference.

    Parameters
    ----------
    vertices : (V, 3) float
    faces : (F, 3) int
    reference : (vertices (M, 3), faces (G, 3)), optional; the cameras then frame its box
    box : (N, 3) float, optional, points whose box the cameras frame without a reference (else the mesh's)
    size : int, image side of each view
    reference_views : Views, optional, the reference already rendered through the same cameras

    Returns
    -------
    dict : back_face_share; with a reference also silhouette_iou and normal_angle.
    """
    frame = reference[0] if reference is not None else box if box is not None else vertices
    cams = cameras(frame, size)
    mine = render_views(vertices, faces, cams)
    out = {"back_face_share": back_face_share(mine)}
    if reference is not None:
        ref = reference_views if reference_views is not None else render_views(*reference, cams)
        out.update(silhouette_iou=silhouette_iou(mine, ref), normal_angle=normal_angle(mine, ref))
    return out
