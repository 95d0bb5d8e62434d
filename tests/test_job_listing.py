"""Retention and listing: every job states ``expires_at``; ``GET /v1/jobs`` pages through a key's jobs, newest
first.  Apps without a worker: the jobs stay queued until a test cancels them."""

from __future__ import annotations

from datetime import datetime, timedelta

import httpx
import pytest
from stack import assert_error, make_settings, post, sphere_points, xyz_bytes

from fastmesh_jobs.store import Store
from service.listing import SCAN_BUDGET, decode_cursor, encode_cursor
from service.processes import ServedApp

BALL = xyz_bytes(sphere_points())
ONE = {"Authorization": "Bearer key-one"}
TWO = {"Authorization": "Bearer key-two"}


@pytest.fixture(scope="module")
def keyed(redis_url):
    app = ServedApp(make_settings(redis_url, "listing", api_keys=["key-one", "key-two"], max_queue_depth=50,
                                  retention_seconds=7200))
    yield app
    app.stop()


def listing(app, headers, **query) -> httpx.Response:
    return httpx.get(f"{app.url}/v1/jobs", params=query, headers=headers, timeout=30)


def every_page(app, headers, **query) -> list[str]:
    ids, cursor = [], None
    for _ in range(50):
        page = listing(app, headers, **query, **({"cursor": cursor} if cursor else {})).json()
        ids += [j["id"] for j in page["jobs"]]
        cursor = page["next_cursor"]
        if cursor is None:
            return ids
    raise AssertionError("no last page")


def when(iso: str) -> datetime:
    return datetime.fromisoformat(iso)


def test_expires_at_is_retention_after_creation_then_after_finishing(keyed):
    job = post(keyed.url, "ball.xyz", BALL, headers=ONE).json()
    assert when(job["expires_at"]) - when(job["created_at"]) == timedelta(seconds=7200)
    cancelled = httpx.delete(f"{keyed.url}/v1/jobs/{job['id']}", headers=ONE).json()
    assert when(cancelled["expires_at"]) - when(cancelled["finished_at"]) == timedelta(seconds=7200)
    store = Store(keyed.settings)
    assert 7190 < store.redis.ttl(store.k_job(job["id"])) <= 7200  # what Redis does is what the job says


def test_listing_pages_newest_first_per_key(keyed):
    mine = [post(keyed.url, f"b{i}.xyz", BALL, headers=ONE).json()["id"] for i in range(5)]
    theirs = post(keyed.url, "t.xyz", BALL, headers=TWO).json()["id"]
    page = listing(keyed, ONE, limit=2).json()
    assert [j["id"] for j in page["jobs"]] == mine[::-1][:2]
    assert page["jobs"][0]["input"]["filename"] == "b4.xyz" and "expires_at" in page["jobs"][0]
    everything = every_page(keyed, ONE, limit=2)
    assert everything[:5] == mine[::-1] and theirs not in everything
    assert len(everything) == len(set(everything))
    assert every_page(keyed, TWO) == [theirs]
    # A deleted job leaves the listing.
    httpx.delete(f"{keyed.url}/v1/jobs/{mine[2]}", headers=ONE)  # cancels
    httpx.delete(f"{keyed.url}/v1/jobs/{mine[2]}", headers=ONE)  # deletes
    assert mine[2] not in every_page(keyed, ONE, limit=3)


def test_listing_filters_by_status(keyed):
    ids = [post(keyed.url, "s.xyz", BALL, headers=TWO).json()["id"] for _ in range(3)]
    httpx.delete(f"{keyed.url}/v1/jobs/{ids[1]}", headers=TWO)
    assert every_page(keyed, TWO, status="cancelled") == [ids[1]]
    queued = every_page(keyed, TWO, status="queued", limit=1)
    assert queued[:2] == [ids[2], ids[0]] and ids[1] not in queued
    assert every_page(keyed, TWO, status="failed") == []


def test_a_rare_status_is_found_past_the_scan_budget(keyed):
    """A page reads a bounded number of entries; the next_cursor carries on to the rest."""
    store = Store(keyed.settings)
    owner = "listing-budget-owner"
    first = store.create(owner, {}, {"filename": "x.xyz"}, b"", 0.0)
    assert store.cancel(first)
    many = [store.create(owner, {}, {"filename": "x.xyz"}, b"", 0.0) for _ in range(SCAN_BUDGET + 20)]
    from service.listing import list_jobs

    page = list_jobs(store, owner, "cancelled", 10, None)
    assert page["jobs"] == [] and page["next_cursor"] is not None
    page = list_jobs(store, owner, "cancelled", 10, page["next_cursor"])
    assert [j["id"] for j in page["jobs"]] == [first] and page["next_cursor"] is None
    for job_id in (first, *many):
        store.delete(job_id)
    store.queue.empty()


def test_cursor_ties_and_round_trip(keyed):
    """Jobs created in the same instant are neither skipped nor repeated across pages."""
    store = Store(keyed.settings)
    owner = "listing-ties-owner"
    ids = sorted(f"{i:032x}" for i in range(7))
    store.redis.zadd(store.k_owned(owner), {i: 1000.5 for i in ids})
    for i in ids:
        store.redis.hset(store.k_job(i), mapping={"owner": owner, "status": "queued", "created_at": "1000.5"})
    from service.listing import list_jobs

    seen, cursor = [], None
    while True:
        page = list_jobs(store, owner, None, 3, cursor)
        seen += [j["id"] for j in page["jobs"]]
        cursor = page["next_cursor"]
        if cursor is None:
            break
    assert seen == ids[::-1]
    assert decode_cursor(encode_cursor(1000.5, ids[0])) == (1000.5, ids[0])
    store.redis.delete(store.k_owned(owner), *[store.k_job(i) for i in ids])


@pytest.mark.parametrize("query, field", [
    ({"limit": 0}, "limit"), ({"limit": 101}, "limit"), ({"limit": "ten"}, "limit"),
    ({"status": "done"}, "status"), ({"status": ""}, "status"),
    ({"cursor": "not-a-cursor"}, "cursor"), ({"cursor": encode_cursor(float("inf"), "0" * 32)}, "cursor"),
    ({"cursor": encode_cursor(1.0, "../etc")}, "cursor"),
])
def test_bad_listing_queries_are_422_naming_the_field(keyed, query, field):
    err = assert_error(listing(keyed, ONE, **query), 422, "invalid_parameter")
    assert err["message"].startswith(field), err


def test_listing_needs_a_key(keyed):
    assert_error(httpx.get(f"{keyed.url}/v1/jobs"), 401, "unauthorized")
