"""``GET /v1/jobs``: an API key's jobs, newest first, a page at a time.

The store indexes each key's jobs by creation time (``P:owned:<owner>``, a sorted set written with the job,
:meth:`fastmesh_jobs.store.Store.create`).  A page walks that index from the cursor down; entries whose job has
expired or was deleted are dropped from it as they are met.  A status filter reads at most
:data:`SCAN_BUDGET` entries per page, so a page of a rare status may hold fewer than ``limit`` jobs and
still have a ``next_cursor``: a client reads on while ``next_cursor`` is not null.
"""

from __future__ import annotations

import base64
import binascii
import math

from fastmesh_jobs.store import Store

from .deps import ID_RE
from .errors import ApiError

MAX_LIMIT = 100  # jobs on one page
SCAN_BUDGET = 500  # index entries one page reads at most (a status filter skips the others)


def encode_cursor(score: float, job_id: str) -> str:
    """An opaque cursor: the page continues below (creation time, job id)."""
    return base64.urlsafe_b64encode(f"{score!r}:{job_id}".encode()).decode().rstrip("=")


def decode_cursor(cursor: str) -> tuple[float, str]:
    """``(creation time, job id)`` of a cursor from :func:`encode_cursor`.

    Raises
    ------
    ApiError
        422 ``invalid_parameter`` naming ``cursor``.
    """
    try:
        text = base64.urlsafe_b64decode(cursor + "=" * (-len(cursor) % 4)).decode()
        score, job_id = text.split(":")
        score = float(score)
        if not math.isfinite(score) or not ID_RE.fullmatch(job_id):
            raise ValueError
    except (ValueError, binascii.Error, UnicodeDecodeError):
        raise ApiError(422, "invalid_parameter", "cursor: not a cursor this API returned; "
                                                 "leave it out for the first page") from None
    return score, job_id


def _entries(store: Store, key: str, below: tuple[float, str] | None, count: int) -> list[tuple[str, float]]:
    """Up to ``count`` index entries ``(job id, created)`` after ``below`` in newest-first order.

    Entries of one creation time come in descending id order (ZREVRANGEBYSCORE), so "after" is: an earlier
    time, or the same time and a smaller id.
    """
    if below is None:
        return [(m.decode(), s) for m, s in store.redis.zrevrangebyscore(key, "+inf", "-inf", start=0, num=count,
                                                                          withscores=True)]
    score, last = below
    ties = store.redis.zrangebyscore(key, score, score)  # the few entries sharing the cursor's time
    skip = sum(1 for m in ties if m.decode() >= last)
    rows = store.redis.zrevrangebyscore(key, score, "-inf", start=skip, num=count, withscores=True)
    return [(m.decode(), s) for m, s in rows]


def list_jobs(store: Store, owner: str, status: str | None, limit: int, cursor: str | None) -> dict:
    """A page of ``owner``'s jobs (``service.schemas.JobPage``): at most ``limit`` jobs, newest first, of
    ``status`` when given, after ``cursor``."""
    key = store.k_owned(owner)
    below = decode_cursor(cursor) if cursor else None
    jobs: list[dict] = []
    read = 0
    more = True
    while len(jobs) < limit and read < SCAN_BUDGET:
        chunk = min(SCAN_BUDGET - read, max(limit - len(jobs), 1) if status is None else 100)
        rows = _entries(store, key, below, chunk)
        if not rows:
            more = False
            break
        with store.redis.pipeline() as pipe:
            for job_id, _ in rows:
                pipe.hmget(store.k_job(job_id), "status", "owner")
            found = pipe.execute()
        gone = []
        for (job_id, score), (st, who) in zip(rows, found, strict=True):
            read += 1
            below = (score, job_id)
            if st is None or who is None or who.decode() != owner:
                gone.append(job_id)
            elif status is None or st.decode() == status:
                job = store.get(job_id)
                if job is not None:
                    jobs.append(store.public(job))
            if len(jobs) == limit:
                break
        if gone:
            store.redis.zrem(key, *gone)
        if len(rows) < chunk and below == (rows[-1][1], rows[-1][0]):
            more = False  # the index ended in this chunk and every entry of it was read
            break
    if more and below is not None and not _entries(store, key, below, 1):
        more = False
    return {"jobs": jobs, "next_cursor": encode_cursor(*below) if more and below is not None else None}
