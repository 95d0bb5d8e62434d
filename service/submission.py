"""Steps every submission takes, one file (``POST /v1/jobs``) or several (``POST /v1/batches``).

The routes in :mod:`service.routes.jobs` and :mod:`service.routes.batches` call these in order: charge the
submit rate limit, vet the ``callback_url``, then per file take a parsing slot, read and parse it.
"""

from __future__ import annotations

import contextlib

from fastapi import UploadFile

from fastmesh_jobs.settings import Settings
from fastmesh_jobs.store import Store

from .errors import ApiError
from .parse_slots import FairSlots
from .webhooks import UnsafeUrl, new_webhook, vet_at_submit


def charge(store: Store, settings: Settings, bucket: str, count: int = 1) -> None:
    """Count ``count`` submissions against the key's per-minute limit.

    Raises
    ------
    ApiError
        429 ``rate_limited`` with ``Retry-After`` past the limit.
    """
    for _ in range(count):
        wait = store.rate_hit("submit", bucket, settings.submit_rate_limit_per_minute)
        if wait:
            raise ApiError(429, "rate_limited", f"more than {settings.submit_rate_limit_per_minute} submissions "
                                                "per minute for this key", {"Retry-After": str(wait)})


def webhook_of(settings: Settings, callback_url: str | None) -> dict | None:
    """The ``webhook`` field of jobs submitted with ``callback_url`` (None without one).

    Raises
    ------
    ApiError
        422 naming ``callback_url``: webhooks are off (no ``webhook_secret``), or the URL may not be called
        (:func:`service.webhooks.vet`).
    """
    if callback_url is None:
        return None
    if settings.webhook_secret is None:
        raise ApiError(422, "webhooks_disabled", "callback_url: this server sends no webhooks "
                                                 "(FASTMESH_WEBHOOK_SECRET is unset)")
    try:
        vet_at_submit(callback_url, settings.webhook_allow_private)
    except UnsafeUrl as e:
        raise ApiError(422, "invalid_parameter", f"callback_url: {e}") from None
    return new_webhook(callback_url)


@contextlib.contextmanager
def parse_slot(slots: FairSlots, settings: Settings, owner: str):
    """Hold one of the app's upload-reading slots for ``owner`` (the key's rate-limit bucket).  Reading and parsing
    hold up to a few times the upload in memory: a fixed number at once keeps the API's peak a known multiple of
    the limits; beyond it the client is told to come back.  One key never holds them all
    (:class:`service.parse_slots.FairSlots`).

    Raises
    ------
    ApiError
        429 ``busy`` when no slot frees within ``parse_wait_seconds``, or the key's share is in use that long.
    """
    if not slots.acquire(owner, timeout=settings.parse_wait_seconds):
        mine = slots.held(owner)
        why = (f"this key's uploads hold {mine} of the {slots.capacity} upload-reading slots, the most one key may"
               if mine >= slots.per_owner else f"{settings.max_concurrent_parses} uploads are being read")
        raise ApiError(429, "busy", f"{why}; retry shortly", {"Retry-After": "2"})
    try:
        yield
    finally:
        slots.release(owner)


def read_upload(file: UploadFile, settings: Settings) -> bytes:
    """The uploaded file's bytes.

    Raises
    ------
    ApiError
        413 ``too_large`` above ``max_upload_bytes``.
    """
    data = file.file.read(settings.max_upload_bytes + 1)
    if len(data) > settings.max_upload_bytes:
        raise ApiError(413, "too_large", f"upload larger than the {settings.max_upload_bytes} byte limit")
    return data
