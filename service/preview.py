"""PNG previews of a job, and its input points for overlays: ``/v1/jobs/{id}/preview.png`` and ``.../input.ply``.

A preview shows the result mesh once the job has succeeded, and the input (point cloud or dense
mesh) before that, or when the job failed or was cancelled, so a client always has something to
show.  Rendering is :mod:`fastmesh.preview.render` (numpy z-buffer, CPU only), and ``input.ply`` a sample of the
stored input, both in a small pool of memory-capped child processes (:mod:`service.render_pool`), so the API's
memory does not grow with the inputs; both take one of ``max_concurrent_renders`` slots, and a request
waiting for one holds no input in memory.  Concurrent requests for the same overlay share one sample.

Each (job, what, size, wireframe) is rendered once: concurrent requests for it wait for the one
render (single flight), whose PNG is cached in Redis for ``cache_seconds`` (at most the job's
retention).  Only a few sizes are rendered (another is refused with 422, never answered with an image of
another size), so a job has at most a few dozen cached variants.
The stored input is read only once a render slot is free, and when more distinct renders are
pending than ``max_pending``, a request is answered 503 + Retry-After at once.  Access is that of
the other ``/v1`` routes: the same :data:`service.deps.Owner` dependency (API key, rate limit) and
:func:`service.deps.owned_job` lookup (another key's job is a 404).

The routes are :data:`router`'s; ``create_app`` includes it and keeps the app's :class:`Previews` (the render
pool, the renders pending) on ``app.state.previews``, which the routes reach through :data:`PreviewsDep`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import anyio
from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import Response

from fastmesh_jobs.store import Store

from .children import ChildFailed, ChildShapeError
from .deps import JobId, Owner, StoreDep, owned_job
from .errors import ApiError
from .render_pool import RenderPool
from .schemas import error_responses

# KEYS: the job's hash, its preview hash.  ARGV: field, PNG, ttl.  A render that finishes after the job was
# deleted must not leave its PNG behind: the preview is cached only while the job exists.
_CACHE_IF_JOB = """
if redis.call('EXISTS', KEYS[1]) == 0 then return 0 end
redis.call('HSET', KEYS[2], ARGV[1], ARGV[2])
redis.call('EXPIRE', KEYS[2], ARGV[3])
return 1
"""


@dataclass(frozen=True)
class PreviewConfig:
    """Limits of the preview routes."""

    min_size: int = 64  # pixels; smaller is useless, and the renderer frames poorly below ~32
    max_size: int = 1024  # pixels; a 1024 px render of a dense input mesh takes a few seconds
    default_size: int = 512
    # The sizes served: each one a render of its own and a cache entry, so few of them.
    sizes: tuple[int, ...] = (64, 128, 256, 512, 1024)
    # Renders are CPU-bound numpy: more at once only slow each other down (and the API with them).
    max_concurrent_renders: int = 2
    max_pending: int = 8  # distinct renders running or waiting for a slot; beyond it 503 at once
    render_wait_seconds: float = 30.0  # a render not done in this time answers 503
    cache_seconds: int = 3600  # how long a rendered preview stays in Redis (at most the job's retention)
    overlay_points: int = 20_000  # default points in input.ply: enough to read the shape, ~240 KB
    max_overlay_points: int = 200_000


DEFAULT_PREVIEW = PreviewConfig()


def cache_key(store: Store, job_id: str) -> str:
    """One Redis hash per job holds all its previews, so deleting the job deletes them in one go."""
    return store.k_preview(job_id)


def cache_field(of: str, size: int, wireframe: bool) -> str:
    return f"{of}:{size}:{int(wireframe)}"


def check_size(size: int, sizes: tuple[int, ...]) -> int:
    """``size`` when it is one of the rendered ``sizes``.

    Raises
    ------
    ApiError
        422 ``invalid_parameter`` naming the sizes (an image of another size than asked would break a layout
        that relies on it).
    """
    if size not in sizes:
        raise ApiError(422, "invalid_parameter", f"size: {size} px is not one of the rendered sizes "
                                                 f"{', '.join(map(str, sizes))}; ask for one of them and scale "
                                                 "the image where you need another")
    return size


def preview_blob(store: Store, job: dict) -> tuple[str, bytes]:
    """What to draw for ``job``, as stored: ``("result", npz)`` once succeeded, else ``("input", npz)``.

    Raises
    ------
    ApiError
        404 when neither the result nor the input is stored any more (deleted or expired).
    """
    if job["status"] == "succeeded":
        data = store.get_result(job["id"], "npz")
        if data is not None:
            return "result", data
    blob = store.get_input(job["id"])
    if blob is None:
        raise ApiError(404, "not_found", "nothing to preview: the job's input and result are no longer stored")
    return "input", blob


class _Flight:
    """One render or sample in progress; the requests that asked for the same one wait on ``done``."""

    def __init__(self):
        self.done = anyio.Event()
        self.value = None
        self.error: ApiError | None = None


def busy(why: str) -> ApiError:
    return ApiError(503, "busy", f"{why}; retry shortly", {"Retry-After": "2"})


def child_error(e: Exception, what: str) -> ApiError:
    """The answer to a render or sample that failed in its child process."""
    if isinstance(e, ChildShapeError):
        return ApiError(422, e.code, f"{what}: {e.message}")
    if e.reason == "memory":
        return ApiError(413, "too_large", f"{what}: the input needs more memory than a render may use")
    return busy(f"{what} in time" if e.reason == "deadline" else f"{what} now")


class Previews:
    """An app's previews in the making: ``pool`` holds the render processes (``config.max_concurrent_renders``
    of them), and the renders and samples pending are shared by the requests that ask for the same one.

    The routes are async and their waiting is on the event loop: requests queued for a render hold no thread
    of the pool that every other route (and /healthz) runs in.  Event-loop state only.
    """

    def __init__(self, pool: RenderPool, config: PreviewConfig = DEFAULT_PREVIEW):
        self.pool, self.config = pool, config
        self.flights: dict[str, _Flight] = {}
        self._slots: anyio.Semaphore | None = None  # made on first use, inside the event loop
        self.renders = 0  # renders started, for tests and the benchmark
        self.samples = 0  # input.ply samples started, likewise

    async def slot(self) -> anyio.Semaphore:
        """A render slot, acquired: 503 busy when none frees up within ``render_wait_seconds``."""
        if self._slots is None:
            self._slots = anyio.Semaphore(self.config.max_concurrent_renders)
        with anyio.move_on_after(self.config.render_wait_seconds) as waited:
            await self._slots.acquire()
        if waited.cancelled_caught:
            raise busy("too many previews are being rendered")
        return self._slots

    async def shared(self, name: str, work):
        """``work()``'s value, run in a thread holding a render slot, once for all the requests that ask for
        ``name`` meanwhile (single flight); 503 busy when ``max_pending`` others are pending."""
        flight = self.flights.get(name)
        if flight is None:  # no await between the look-up and the claim: one leader per name
            if len(self.flights) >= self.config.max_pending:
                raise busy(f"{len(self.flights)} previews are waiting to be rendered")
            flight = self.flights[name] = _Flight()
            try:
                await self._lead(flight, work)
            finally:
                self.flights.pop(name, None)
                flight.done.set()
        else:
            with anyio.move_on_after(self.config.render_wait_seconds) as waited:
                await flight.done.wait()
            if waited.cancelled_caught:
                raise busy("the preview is still being rendered")
        if flight.error is not None:
            raise flight.error
        return flight.value

    async def _lead(self, flight: _Flight, work) -> None:
        """Run ``work`` for ``flight``, leaving its value or the error its waiting requests are answered."""
        try:
            held = await self.slot()
            try:
                flight.value = await anyio.to_thread.run_sync(work)
            finally:
                held.release()
        except ApiError as e:
            flight.error = e
        except Exception:  # Redis trouble: the waiting requests get an answer too, the leader the error
            flight.error = busy("the preview failed")
            raise

    def render_and_cache(self, store: Store, job: dict, size: int, wireframe: bool) -> tuple[str, bytes]:
        """(what, PNG) of ``job`` rendered by the pool, and cached.  Runs in a thread, holding a render slot."""
        of, blob = preview_blob(store, job)  # read only now: waiting requests hold no input in memory
        self.renders += 1
        try:
            png = self.pool.render(of, blob, size, wireframe, self.config.render_wait_seconds)
        except (ChildShapeError, ChildFailed) as e:
            raise child_error(e, "cannot render a preview") from None
        del blob
        ttl = max(1, min(self.config.cache_seconds, store.ttl_of(job["id"])))
        store.redis.eval(_CACHE_IF_JOB, 2, store.k_job(job["id"]), cache_key(store, job["id"]),
                         cache_field(of, size, wireframe), png, ttl)
        return of, png

    def overlay(self, store: Store, job_id: str, points: int) -> bytes:
        """``input.ply`` made by the pool.  Runs in a thread holding a render slot: the stored input is read
        only then, so requests waiting for a slot hold nothing."""
        blob = store.get_input(job_id)
        if blob is None:
            raise ApiError(404, "not_found", "the job's input is no longer stored")
        self.samples += 1
        try:
            return self.pool.overlay(blob, points, self.config.render_wait_seconds)
        except (ChildShapeError, ChildFailed) as e:
            raise child_error(e, "cannot sample the input") from None


def get_previews(request: Request) -> Previews:
    return request.app.state.previews


PreviewsDep = Annotated[Previews, Depends(get_previews)]
SIZES = ", ".join(map(str, DEFAULT_PREVIEW.sizes))

router = APIRouter(tags=["jobs"])


@router.get("/v1/jobs/{job_id}/preview.png", response_class=Response,
            summary="PNG preview: the result mesh, or the input before the result exists",
            description=f"The image is `size` px square, one of {SIZES} (a few sizes keep the cache small; another "
                        "is refused with 422).",
            responses={**error_responses(401, 404, 422, 429, 503),
                       200: {"description": "The preview; `X-Preview-Of` says whether it shows the `result` or "
                                            "the `input`",
                             "content": {"image/png": {"schema": {"type": "string", "format": "binary"}}},
                             "headers": {"X-Preview-Of": {"schema": {"type": "string",
                                                                     "enum": ["result", "input"]}}}}})
async def preview(job_id: JobId, who: Owner, store: StoreDep, previews: PreviewsDep,
                  size: int = Query(DEFAULT_PREVIEW.default_size, ge=DEFAULT_PREVIEW.min_size,
                                    le=DEFAULT_PREVIEW.max_size, description=f"Image side in pixels: {SIZES}.",
                                    examples=[512]),
                  wireframe: bool = Query(False, description="Overlay the edges of the visible faces.",
                                          examples=[True])) -> Response:
    size = check_size(size, previews.config.sizes)
    job = await anyio.to_thread.run_sync(owned_job, store, job_id, who)
    of = "result" if job["status"] == "succeeded" else "input"
    field = cache_field(of, size, wireframe)
    png = await anyio.to_thread.run_sync(store.redis.hget, cache_key(store, job_id), field)
    if png is None:
        of, png = await previews.shared(f"{job_id}|{field}",
                                        lambda: previews.render_and_cache(store, job, size, wireframe))
    # A result preview never changes; an input preview turns into the result's at the same URL.
    cache = "private, max-age=86400" if of == "result" else "no-cache"
    return Response(png, media_type="image/png", headers={"Cache-Control": cache, "X-Preview-Of": of})


@router.get("/v1/jobs/{job_id}/input.ply", response_class=Response,
            summary="The input as points (PLY), to overlay on the result",
            responses={**error_responses(401, 404, 422, 429, 503),
                       200: {"description": "Binary PLY point cloud in the input's original frame",
                             "content": {"application/ply": {"schema": {"type": "string", "format": "binary"}}}}})
async def input_points(job_id: JobId, who: Owner, store: StoreDep, previews: PreviewsDep,
                       points: int = Query(DEFAULT_PREVIEW.overlay_points, ge=1,
                                           le=DEFAULT_PREVIEW.max_overlay_points,
                                           description="At most this many points (evenly picked or sampled).")
                       ) -> Response:
    await anyio.to_thread.run_sync(owned_job, store, job_id, who)
    ply = await previews.shared(f"{job_id}|input.ply|{points}", lambda: previews.overlay(store, job_id, points))
    return Response(ply, media_type="application/ply",
                    headers={"Cache-Control": "private, max-age=86400",
                             "Content-Disposition": f'inline; filename="{job_id}-input.ply"'})
