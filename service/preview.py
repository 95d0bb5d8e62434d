"""PNG previews of a job, and its input points for overlays: ``/v1/jobs/{id}/preview.png`` and ``.../input.ply``.

A preview shows the result mesh once the job has succeeded, and the input (point cloud or dense
mesh) before that, or when the job failed or was cancelled, so a client always has something to
show.  Rendering is :mod:`fastmesh.render` (numpy z-buffer, CPU only) on first request; the PNG is
then cached in Redis per (job, what, size, wireframe) with the job's own retention time, so
every later request is a single GET.  Access is that of the other ``/v1`` routes: the same
``owner`` dependency (API key, rate limit) and ``job_of`` lookup (another key's job is a 404).

Installed by ``create_app`` with ``app.include_router(preview_router(store, owner, job_of))``.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from fastapi import APIRouter, Depends, Path, Query
from fastapi.responses import Response

from fastmesh.io import ShapeError, sample_triangles
from fastmesh.render import render_mesh, render_points, render_shape, to_png

from .errors import ApiError
from .schemas import error_responses
from .store import Store, mesh_from_bytes, shape_from_bytes

JOB_ID = Path(..., description="Job id as returned by POST /v1/jobs.",
              examples=["3f2b9c1d4e5f40718293a4b5c6d7e8f9"])


@dataclass(frozen=True)
class PreviewConfig:
    """Limits of the preview routes."""

    min_size: int = 64  # pixels; smaller is useless, and the renderer frames poorly below ~32
    max_size: int = 1024  # pixels; a 1024 px render of a dense input mesh takes a few seconds
    default_size: int = 512
    # Renders are CPU-bound numpy: more at once only slow each other down (and the API with them).
    max_concurrent_renders: int = 2
    render_wait_seconds: float = 30.0  # queueing for a render slot longer than this answers 503
    overlay_points: int = 20_000  # default points in input.ply: enough to read the shape, ~240 KB
    max_overlay_points: int = 200_000


DEFAULT_PREVIEW = PreviewConfig()


def cache_key(store: Store, job_id: str) -> str:
    """One Redis hash per job holds all its previews, so deleting the job deletes them in one go."""
    return store.k_preview(job_id)


def cache_field(of: str, size: int, wireframe: bool) -> str:
    return f"{of}:{size}:{int(wireframe)}"


def preview_source(store: Store, job: dict) -> tuple[str, object]:
    """What to draw for ``job``: ``("result", (vertices, faces))`` once succeeded, else ``("input", Shape)``.

    Raises
    ------
    ApiError
        404 when neither the result nor the input is stored any more (deleted or expired).
    """
    if job["status"] == "succeeded":
        data = store.get_result(job["id"], "npz")
        if data is not None:
            return "result", mesh_from_bytes(data)
    blob = store.get_input(job["id"])
    if blob is None:
        raise ApiError(404, "not_found", "nothing to preview: the job's input and result are no longer stored")
    return "input", shape_from_bytes(blob)


def render_preview(of: str, source, size: int, wireframe: bool) -> bytes:
    """PNG bytes of a result mesh ``(vertices, faces)`` or an input ``Shape``.

    A result without faces (a degenerate generation) is drawn as its vertices, so the preview still
    shows what came out.  Raises :class:`ShapeError` when there is nothing drawable.
    """
    if of == "result":
        vertices, faces = source
        if len(faces):
            img = render_mesh(vertices, faces, size=size, wireframe=wireframe)
        else:
            img = render_points(vertices, size=size)
    else:
        img = render_shape(source, size=size, wireframe=wireframe and source.faces is not None)
    return to_png(img)


def overlay_points(shape, n: int) -> np.ndarray:
    """Up to ``n`` points of an input shape, (n, 3) float32, input frame: evenly picked points of a cloud,
    area-weighted surface samples of a mesh (its vertices cluster where detail is, not where the surface is)."""
    if shape.faces is None:
        v = shape.vertices
        idx = np.arange(len(v)) if len(v) <= n else np.linspace(0, len(v) - 1, n).astype(np.int64)
        return v[idx].astype(np.float32)
    points, _ = sample_triangles(np.asarray(shape.vertices, np.float64), shape.faces, n, np.random.default_rng(0))
    return points


def points_ply(points: np.ndarray) -> bytes:
    """Binary little-endian PLY of (N, 3) points (float32 x, y, z), the format three.js's PLYLoader reads."""
    p = np.ascontiguousarray(points, dtype="<f4")
    header = (f"ply\nformat binary_little_endian 1.0\ncomment fastmesh input points\nelement vertex {len(p)}\n"
              "property float x\nproperty float y\nproperty float z\nend_header\n")
    return header.encode("ascii") + p.tobytes()


def preview_router(store: Store, owner: Callable, job_of: Callable[[str, str], dict],
                   config: PreviewConfig = DEFAULT_PREVIEW) -> APIRouter:
    """Routes for previews.  ``owner`` is the app's auth dependency, ``job_of(id, who)`` its job lookup."""
    router = APIRouter(tags=["jobs"])
    slots = threading.BoundedSemaphore(config.max_concurrent_renders)

    @router.get("/v1/jobs/{job_id}/preview.png", response_class=Response,
                summary="PNG preview: the result mesh, or the input before the result exists",
                responses={**error_responses(401, 404, 422, 429, 503),
                           200: {"description": "The preview; `X-Preview-Of` says whether it shows the `result` "
                                                "or the `input`",
                                 "content": {"image/png": {"schema": {"type": "string", "format": "binary"}}},
                                 "headers": {"X-Preview-Of": {"schema": {"type": "string",
                                                                         "enum": ["result", "input"]}}}}})
    def preview(job_id: str = JOB_ID,
                size: int = Query(config.default_size, ge=config.min_size, le=config.max_size,
                                  description="Image side in pixels.", examples=[512]),
                wireframe: bool = Query(False, description="Overlay the edges of the visible faces.",
                                        examples=[True]),
                who: str = Depends(owner)) -> Response:
        job = job_of(job_id, who)
        of = "result" if job["status"] == "succeeded" else "input"
        key = cache_key(store, job_id)
        png = store.r.hget(key, cache_field(of, size, wireframe))
        if png is None:
            of, source = preview_source(store, job)
            if not slots.acquire(timeout=config.render_wait_seconds):
                raise ApiError(503, "busy", "too many previews are being rendered; retry shortly",
                               {"Retry-After": "2"})
            try:
                png = render_preview(of, source, size, wireframe)
            except ShapeError as e:
                raise ApiError(422, e.code, f"cannot render a preview: {e.message}") from None
            finally:
                slots.release()
            with store.r.pipeline() as tx:
                tx.hset(key, cache_field(of, size, wireframe), png)
                tx.expire(key, store.ttl_of(job_id))
                tx.execute()
        # A result preview never changes; an input preview turns into the result's at the same URL.
        cache = "private, max-age=86400" if of == "result" else "no-cache"
        return Response(png, media_type="image/png", headers={"Cache-Control": cache, "X-Preview-Of": of})

    @router.get("/v1/jobs/{job_id}/input.ply", response_class=Response,
                summary="The input as points (PLY), to overlay on the result",
                responses={**error_responses(401, 404, 422, 429, 503),
                           200: {"description": "Binary PLY point cloud in the input's original frame",
                                 "content": {"application/ply": {"schema": {"type": "string",
                                                                            "format": "binary"}}}}})
    def input_points(job_id: str = JOB_ID,
                     points: int = Query(config.overlay_points, ge=1, le=config.max_overlay_points,
                                         description="At most this many points (evenly picked or sampled)."),
                     who: str = Depends(owner)) -> Response:
        job_of(job_id, who)
        blob = store.get_input(job_id)
        if blob is None:
            raise ApiError(404, "not_found", "the job's input is no longer stored")
        try:
            pts = overlay_points(shape_from_bytes(blob), points)
        except ShapeError as e:
            raise ApiError(422, e.code, e.message) from None
        return Response(points_ply(pts), media_type="application/ply",
                        headers={"Cache-Control": "private, max-age=86400",
                                 "Content-Disposition": f'inline; filename="{job_id}-input.ply"'})

    return router
