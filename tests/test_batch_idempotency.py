"""``POST /v1/batches`` with an ``Idempotency-Key``: the key names the whole batch.  A retry of the same batch
gets its jobs (200); one with a file more or fewer, or another file, is ``409 idempotency_conflict`` and makes
no job.  An app without a worker (jobs stay queued)."""

from __future__ import annotations

import httpx
import pytest
from stack import assert_error, make_settings, sphere_points, xyz_bytes

from fastmesh_jobs.store import Store
from service.processes import ServedApp

BALLS = [xyz_bytes(sphere_points(seed=i)) for i in range(3)]


@pytest.fixture(scope="module")
def idle(redis_url):
    app = ServedApp(make_settings(redis_url, "batch-idem", max_queue_depth=20, max_batch_files=4))
    yield app
    app.stop()


def batch(app, files: list[tuple[str, bytes]], key: str) -> httpx.Response:
    return httpx.post(f"{app.url}/v1/batches", files=[("files", f) for f in files],
                      headers={"Idempotency-Key": key}, timeout=60)


def queued(app) -> set[str]:
    store = Store(app.settings)
    return {m.decode() for m in store.redis.zrange(store.k_queued, 0, -1)}


@pytest.mark.parametrize("retry", [
    [("a.xyz", BALLS[0]), ("b.xyz", BALLS[1]), ("c.xyz", BALLS[2])],  # a file more
    [("a.xyz", BALLS[0])],  # a file fewer
    [("a.xyz", BALLS[0]), ("c.xyz", BALLS[2])],  # another second file
], ids=["more", "fewer", "other"])
def test_a_batch_key_reused_for_a_different_batch_is_409_and_makes_no_job(idle, retry, request):
    key = f"batch-{request.node.callspec.id}"
    first = batch(idle, [("a.xyz", BALLS[0]), ("b.xyz", BALLS[1])], key)
    assert first.status_code == 202, first.text
    jobs = set(first.json()["job_ids"])
    assert queued(idle) >= jobs
    before = queued(idle)
    err = assert_error(batch(idle, retry, key), 409, "idempotency_conflict")
    assert "different batch" in err["message"], err
    assert queued(idle) == before  # nothing merged into the batch, nothing new queued
    again = batch(idle, [("a.xyz", BALLS[0]), ("b.xyz", BALLS[1])], key)  # the same batch still gets its jobs
    assert again.status_code == 200 and again.json()["job_ids"] == first.json()["job_ids"], again.text
