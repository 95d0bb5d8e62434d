"""``fastmesh-worker`` processes: model loaded once, progress, cancellation, timeouts, deaths.

Slow jobs are made with ``FASTMESH_DEBUG_STEP_DELAY`` (a sleep in each progress callback of the
real pipeline), so a test can catch a job mid-decode without depending on how fast the machine is.
"""

from __future__ import annotations

import os
import signal
import time

import httpx
import pytest
import redis
from test_service_api import assert_error, make_settings, submit, wait_final

from service.testing import ServedApp, WorkerProcess, redis_for_tests, wait_for

DB = int(os.environ.get("FASTMESH_TEST_REDIS_DB", "13"))
SLOW = "0.05"  # seconds per progress callback: a 64-vertex job decodes for seconds, not milliseconds


@pytest.fixture(scope="module")
def redis_url():
    url, server = redis_for_tests(DB)
    client = redis.Redis.from_url(url)
    client.flushdb()
    yield url
    client.flushdb()
    if server:
        server.stop()


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    from fastmesh.pipeline import Pipeline

    d = tmp_path_factory.mktemp("weights")
    Pipeline.random("tiny", seed=0).save(str(d))
    return str(d)


@pytest.fixture
def env(redis_url, weights, request, tmp_path):
    """A fresh app (own prefix and queue) and a factory of workers, all stopped afterwards."""
    s = make_settings(redis_url, request.node.name[:40], weights=weights, max_attempts=2)
    app = ServedApp(s)
    workers: list[WorkerProcess] = []

    def start(name: str, **extra) -> WorkerProcess:
        w = WorkerProcess(s, f"{request.node.name[:30]}-{name}", tmp_path / f"{name}.log", **extra)
        workers.append(w)
        return w.wait_ready()

    yield app, s, start
    for w in workers:
        if w.proc.poll() is None:
            os.kill(w.pid, signal.SIGCONT)  # in case a test left it stopped
        w.stop()
    app.stop()


def job(app, job_id):
    return httpx.get(f"{app.url}/v1/jobs/{job_id}").json()


def wait_running(app, job_id, stage="vertices"):
    return wait_for(lambda: (j := job(app, job_id))["status"] == "running" and j["progress"]["stage"] == stage
                    and j, 30, 0.02, what=f"job {job_id} to decode")


def test_pipeline_loaded_once_per_process(env):
    app, s, start = env
    w = start("w")
    ids = [submit(app.url, max_vertices=10, seed=i).json()["id"] for i in range(3)]
    for i in ids:
        assert wait_final(app.url, i)["status"] == "succeeded"
    info = wait_for(lambda: (inf := redis.Redis.from_url(s.redis_url).hgetall(f"{s.redis_prefix}:worker:{w.name}"))
                    and inf[b"jobs"] == b"3" and inf, 10, what="worker info to count 3 jobs")
    assert info[b"loads"] == b"1", info  # three jobs, one model load
    assert info[b"pid"] == str(w.pid).encode()
    assert w.log().count("pipeline loaded") == 1


def test_progress_moves_while_decoding(env):
    app, _, start = env
    start("w", FASTMESH_DEBUG_STEP_DELAY=SLOW)
    job_id = submit(app.url, max_vertices=64).json()["id"]
    seen = set()

    def two_fractions():
        j = job(app, job_id)
        if j["status"] == "running" and j["progress"]["stage"] == "vertices":
            seen.add(j["progress"]["fraction"])
        return len(seen) >= 3

    wait_for(two_fractions, 30, 0.05, what="decoder progress to move")
    assert all(0 <= f <= 1 for f in seen)
    httpx.delete(f"{app.url}/v1/jobs/{job_id}")


def test_cancel_running_job_frees_the_worker(env):
    app, s, start = env
    w = start("w", FASTMESH_DEBUG_STEP_DELAY=SLOW)
    slow = submit(app.url, max_vertices=64).json()["id"]
    wait_running(app, slow)
    r = httpx.delete(f"{app.url}/v1/jobs/{slow}")
    assert r.status_code == 200 and r.json()["status"] == "cancelled"
    assert_error(httpx.get(f"{app.url}/v1/jobs/{slow}/result"), 409, "job_cancelled")
    nxt = submit(app.url, max_vertices=5).json()["id"]
    assert wait_final(app.url, nxt, timeout=20)["status"] == "succeeded"
    assert job(app, slow)["status"] == "cancelled"
    assert f"job {slow} attempt 1 stopped (cancelled or superseded)" in w.log()  # stopped, not run to the end
    client = redis.Redis.from_url(s.redis_url)
    assert client.scard(f"{s.redis_prefix}:running") == 0
    assert not client.exists(f"{s.redis_prefix}:result:{slow}:glb")


def test_cancel_queued_job_never_runs(env):
    app, s, start = env
    w = start("w", FASTMESH_DEBUG_STEP_DELAY=SLOW)
    first = submit(app.url, max_vertices=12).json()["id"]
    wait_running(app, first)
    os.kill(w.pid, signal.SIGSTOP)  # hold the worker so the next job stays queued
    try:
        queued = submit(app.url, max_vertices=5).json()["id"]
        assert job(app, queued)["status"] == "queued"
        assert httpx.delete(f"{app.url}/v1/jobs/{queued}").json()["status"] == "cancelled"
    finally:
        os.kill(w.pid, signal.SIGCONT)
    assert wait_final(app.url, first)["status"] == "succeeded"
    time.sleep(0.5)
    assert job(app, queued)["status"] == "cancelled" and job(app, queued)["started_at"] is None


def test_sigkill_mid_job_is_retried_on_another_worker(env):
    app, s, start = env
    doomed = start("doomed", FASTMESH_DEBUG_STEP_DELAY=SLOW)
    job_id = submit(app.url, max_vertices=20).json()["id"]
    wait_running(app, job_id)
    doomed.proc.send_signal(signal.SIGKILL)
    doomed.proc.wait()
    # The API's reaper sees the heartbeat expire and queues attempt 2.
    j = wait_for(lambda: (j := job(app, job_id))["status"] == "queued" and j, 15, what="requeue after SIGKILL")
    assert j["progress"]["stage"] == "queued"
    start("rescuer")
    final = wait_final(app.url, job_id)
    assert final["status"] == "succeeded", final
    client = redis.Redis.from_url(s.redis_url)
    assert client.hget(f"{s.redis_prefix}:job:{job_id}", "attempt") == b"2"
    assert int(client.hget(f"{s.redis_prefix}:stats:jobs", "retried")) == 1
    assert 'fastmesh_jobs_total{status="retried"} 1.0' in httpx.get(f"{app.url}/metrics").text


def test_sigkill_on_every_attempt_fails_clearly(env):
    app, s, start = env
    job_id = submit(app.url, max_vertices=20).json()["id"]
    for attempt in (1, 2):  # max_attempts = 2
        w = start(f"doomed{attempt}", FASTMESH_DEBUG_STEP_DELAY=SLOW)
        wait_running(app, job_id)
        w.proc.send_signal(signal.SIGKILL)
        w.proc.wait()
        if attempt == 1:
            wait_for(lambda: job(app, job_id)["status"] == "queued", 15, what="requeue after SIGKILL")
    final = wait_final(app.url, job_id, timeout=15)
    assert final["status"] == "failed", final
    assert final["error"]["code"] == "worker_lost" and "2 attempt" in final["error"]["message"]
    assert final["finished_at"] is not None


def test_job_timeout(env):
    app, _, start = env
    start("w", FASTMESH_DEBUG_STEP_DELAY=SLOW, FASTMESH_JOB_TIMEOUT="0.5")
    final = wait_final(app.url, submit(app.url, max_vertices=64).json()["id"], timeout=20)
    assert final["status"] == "failed" and final["error"]["code"] == "timeout", final
    assert "0.5 s" in final["error"]["message"]


def test_sigterm_hands_the_running_job_back(env):
    app, _, start = env
    w = start("leaving", FASTMESH_DEBUG_STEP_DELAY=SLOW)
    job_id = submit(app.url, max_vertices=64).json()["id"]
    wait_running(app, job_id)
    w.proc.send_signal(signal.SIGTERM)
    assert w.proc.wait(20) == 0  # warm shutdown stops the decoder instead of waiting for the job
    assert job(app, job_id)["status"] == "queued"
    assert f"job {job_id} handed back to the queue" in w.log()
    start("next", FASTMESH_DEBUG_STEP_DELAY=SLOW)
    wait_running(app, job_id)  # picked up again by the next worker
    assert httpx.delete(f"{app.url}/v1/jobs/{job_id}").json()["status"] == "cancelled"
