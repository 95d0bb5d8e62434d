"""Operations: ``/healthz`` (the process is up), ``/readyz`` (Redis reachable and a worker alive), ``/metrics``
(behind the API key and rate limit of the ``/v1`` routes)."""

from __future__ import annotations

from fastapi import APIRouter, Response

from ..deps import MetricsDep, Owner, StoreDep
from ..errors import ApiError
from ..schemas import Health, Ready, error_responses

router = APIRouter(tags=["ops"])


@router.get("/healthz", response_model=Health, summary="The process is up")
async def healthz() -> dict:  # async: answers from the event loop even when every worker thread is busy
    return {"status": "ok"}


@router.get("/readyz", response_model=Ready, summary="Redis reachable and a worker alive",
            responses=error_responses(503))
def readyz(store: StoreDep) -> dict:
    try:
        store.redis.ping()
        workers, depth = len(store.workers_alive()), store.queue_depth()
    except Exception as e:
        raise ApiError(503, "not_ready", f"Redis unreachable: {type(e).__name__}") from None
    if workers == 0:
        raise ApiError(503, "not_ready", "Redis reachable but no worker alive")
    return {"status": "ready", "redis": True, "workers": workers, "queue_depth": depth}


@router.get("/metrics", summary="Prometheus metrics (an API key when the server has keys; rate-limited)",
            response_class=Response,
            responses={**error_responses(401, 429, 503),
                       200: {"content": {"text/plain": {"example": "fastmesh_queue_depth 0.0\n"}}}})
def prometheus(metrics: MetricsDep, who: Owner) -> Response:
    # Each scrape reads Redis: it needs the key of the /v1 routes and counts against their rate limit.
    return Response(metrics.render(), media_type="text/plain; version=0.0.4; charset=utf-8")
