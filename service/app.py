"""The HTTP API: upload a shape, poll the job, download the artist mesh.

``create_app(settings)`` builds the app; ``uvicorn service.app:create_app --factory`` serves it with
settings from the environment.  The routes are in :mod:`service.routes` (jobs, batches, ops), :mod:`service.preview`
and :mod:`service.web`; what they depend on (settings, store, the caller) in :mod:`service.deps`; webhooks
are delivered by a thread :func:`service.webhooks.dispatch_loop` beside the reaper.
"""

from __future__ import annotations

import functools
import threading
from collections.abc import Callable
from contextlib import asynccontextmanager

from fastapi import FastAPI

from fastmesh_jobs.memory import tune_malloc
from fastmesh_jobs.reaper import reap_loop
from fastmesh_jobs.settings import Settings
from fastmesh_jobs.store import Store

from . import errors, preview
from .children import CappedPool
from .deps import ApiKeys
from .forms import generation_defaults
from .middleware import ApiKeyGate, BodyLimit, JsonCORS, RequestMetrics
from .parse_slots import FairSlots
from .preview import DEFAULT_PREVIEW, Previews
from .render_pool import RenderPool
from .routes import batches, jobs, ops
from .routes.jobs import document_settings
from .telemetry import Metrics
from .web.routes import web_router
from .webhooks import dispatch_loop

DESCRIPTION = """Upload a point cloud or a dense mesh, poll the job, download a clean artist-style mesh.

1. `POST /v1/jobs` with a multipart `file` (obj, glb, gltf, ply, stl, off, xyz, txt, npy, npz) -> 202 + job.
2. `GET /v1/jobs/{id}` until `status` is `succeeded` (or `failed` / `cancelled`).
3. `GET /v1/jobs/{id}/result?format=glb` (add `&wait=60` to long-poll instead of step 2).

`POST /v1/batches` submits several files with one set of parameters; `GET /v1/jobs` lists the key's jobs;
`callback_url` has the finished job POSTed to a URL (signed `X-FastMesh-Signature`).

When the server has API keys, send `Authorization: Bearer <key>`; a key sees only its own jobs.
Every error is JSON `{"error": {"code", "message"}}`."""


@asynccontextmanager
async def lifespan(app: FastAPI):
    store, parses, renders = app.state.store, app.state.parses, app.state.renders
    # Jobs of dead workers are requeued by this process too, so they are even when no worker is alive.
    stop = threading.Event()
    threading.Thread(target=reap_loop, args=(store, stop), name="fastmesh-reaper", daemon=True).start()
    # Webhooks are delivered from here, never from a worker (service.webhooks).
    threading.Thread(target=dispatch_loop, args=(store, stop), name="fastmesh-webhooks", daemon=True).start()
    # Parsing and render processes take a second or two to start (longer at their lower priority on a busy
    # machine): started now, the first uploads, previews and input points do not wait for that.
    threading.Thread(target=parses.warm, name="fastmesh-parse-warm", daemon=True).start()
    threading.Thread(target=renders.warm, name="fastmesh-render-warm", daemon=True).start()
    yield
    stop.set()
    renders.close()
    parses.close()


def openapi_of(app: FastAPI, build: Callable[[], dict]) -> dict:
    """``app``'s OpenAPI schema as ``build`` makes it, stating the app's settings where its routes take them."""
    if app.openapi_schema is None:
        document_settings(build(), app.state.settings)
    return app.openapi_schema


def create_app(settings: Settings | None = None, store: Store | None = None) -> FastAPI:
    settings = settings or Settings()
    # Uploads and stored inputs pass through in blocks of MBs: in pages of their own, they go back to the system
    # when freed, so the API's size returns to its baseline after a burst.
    tune_malloc(arenas=None)
    store = store or Store(settings)
    keys = ApiKeys(settings.api_keys)
    metrics = Metrics(store)
    cap = settings.child_memory_mb * 1024 * 1024
    renders = RenderPool(DEFAULT_PREVIEW.max_concurrent_renders, cap)
    parses = CappedPool(settings.max_concurrent_parses, cap, name="fastmesh-parse")

    app = FastAPI(title="FastMesh", version="0.1.0", description=DESCRIPTION, lifespan=lifespan,
                  openapi_tags=[{"name": "jobs", "description": "Submit, watch, download, cancel."},
                                {"name": "ops", "description": "Health, readiness, metrics."}])
    # Read by the dependencies of service.deps (and service.preview's); tests and benchmarks read the children
    # of ``parses`` and ``renders``, and the render counts of ``previews``.
    app.state.settings, app.state.store, app.state.metrics, app.state.keys = settings, store, metrics, keys
    app.state.parses, app.state.renders, app.state.previews = parses, renders, Previews(renders)
    app.state.parse_slots = FairSlots(settings.max_concurrent_parses)  # uploads read at once, fair between keys
    errors.install(app)

    for router in (jobs.router, batches.router, ops.router, preview.router):
        app.include_router(router)
    app.include_router(web_router(settings, generation_defaults()))  # the page at / (service/web)
    app.openapi = functools.partial(openapi_of, app, app.openapi)

    # Each add_middleware wraps the previous ones: CORS ends outermost, so 413s and 429s carry its headers too.
    app.add_middleware(BodyLimit, max_bytes=settings.max_upload_bytes, idle_seconds=settings.body_timeout_seconds,
                       deadline_seconds=settings.upload_deadline_seconds)
    if keys:
        limit = settings.auth_fail_limit_per_minute
        app.add_middleware(ApiKeyGate, owner_of=keys.owner_of,
                           fail_hit=lambda a: store.rate_hit("authfail", a, limit),
                           fail_wait=lambda a: store.rate_wait("authfail", a, limit),
                           admit=lambda a, owner: store.auth_admit(a, owner, limit))
    app.add_middleware(RequestMetrics, metrics=metrics)
    if settings.cors_origins:
        app.add_middleware(JsonCORS, allow_origins=settings.cors_origins,
                           allow_methods=["GET", "POST", "DELETE"],
                           allow_headers=["Authorization", "Idempotency-Key", "Content-Type"],
                           expose_headers=["Location", "Retry-After", "X-Queue-Position"])
    return app
