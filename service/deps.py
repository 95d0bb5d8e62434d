"""What the routes depend on, as ``Annotated`` aliases: the app's settings, store, metrics and upload parsers,
and who is asking.

``create_app`` keeps the app's objects on ``app.state``; the aliases read them from the request, so the
routers are module-level, hold no state of their own, and one process can serve several differently
configured apps.
"""

from __future__ import annotations

import hashlib
import hmac
import re
from typing import Annotated

from fastapi import Depends, Path, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from fastmesh_jobs.settings import Settings
from fastmesh_jobs.store import Store

from .children import CappedPool
from .errors import ApiError
from .parse_slots import FairSlots
from .telemetry import Metrics

ID_RE = re.compile(r"[0-9a-f]{32}")
JobId = Annotated[str, Path(description="Job id as returned by POST /v1/jobs.",
                            examples=["3f2b9c1d4e5f40718293a4b5c6d7e8f9"])]

# Documents the scheme in OpenAPI (the /docs "Authorize" button); checking is ours, for JSON errors.
bearer = HTTPBearer(auto_error=False, description="An API key from FASTMESH_API_KEYS (when set).")


class ApiKeys:
    """The configured API keys.  A key's owner is named by a short hash of it, so job records and rate-limit
    counters in Redis never hold the key itself."""

    def __init__(self, keys: list[str]):
        self._by_owner = {hashlib.sha256(k.encode()).hexdigest()[:16]: k for k in keys}

    def __bool__(self) -> bool:
        return bool(self._by_owner)

    def owner_of(self, token: str) -> str | None:
        """The owner ``token`` is the key of, None when it is none of them (compared in constant time)."""
        token = token.strip().encode()
        return next((h for h, k in self._by_owner.items() if hmac.compare_digest(token, k.encode())), None)


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_store(request: Request) -> Store:
    return request.app.state.store


def get_metrics(request: Request) -> Metrics:
    return request.app.state.metrics


def get_parses(request: Request) -> CappedPool:
    return request.app.state.parses


def get_parse_slots(request: Request) -> FairSlots:
    return request.app.state.parse_slots


SettingsDep = Annotated[Settings, Depends(get_settings)]
StoreDep = Annotated[Store, Depends(get_store)]
MetricsDep = Annotated[Metrics, Depends(get_metrics)]
# Uploads are parsed in these capped child processes (``settings.max_concurrent_parses`` of them) ...
Parses = Annotated[CappedPool, Depends(get_parses)]
# ... while holding one of these slots (service.submission.parse_slot), shared by POST /v1/jobs and /v1/batches.
ParseSlots = Annotated[FairSlots, Depends(get_parse_slots)]


def get_owner(request: Request, settings: SettingsDep, store: StoreDep,
              cred: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]) -> str:
    """Who is asking: the owner of their API key, or 'anonymous' when keys are off.  Rate-limits them (per key,
    or per client address when keys are off) and leaves that bucket in ``request.state.bucket``."""
    keys: ApiKeys = request.app.state.keys
    if keys:
        who = keys.owner_of(cred.credentials if cred else "")
        if who is None:
            raise ApiError(401, "unauthorized", "missing or unknown API key; send 'Authorization: Bearer <key>'",
                           {"WWW-Authenticate": "Bearer"})
        bucket = who
    else:
        who = "anonymous"
        bucket = request.client.host if request.client else "anonymous"
    wait = store.rate_hit("req", bucket, settings.rate_limit_per_minute)
    if wait:
        raise ApiError(429, "rate_limited",
                       f"more than {settings.rate_limit_per_minute} requests per minute for this key",
                       {"Retry-After": str(wait)})
    request.state.bucket = bucket
    return who


Owner = Annotated[str, Depends(get_owner)]


def owned_job(store: Store, job_id: str, who: str) -> dict:
    """The job ``job_id`` of ``who``; 404 otherwise (another key's job is indistinguishable from no job)."""
    job = store.get(job_id) if ID_RE.fullmatch(job_id) else None
    if job is None or job["owner"] != who:
        raise ApiError(404, "not_found", f"no job '{job_id[:64]}'")
    return job
