"""``fastmesh-worker`` processes: model loaded once, progress, cancellation, timeouts, deaths.

Slow jobs are made with ``FASTMESH_DEBUG_STEP_DELAY`` (a sleep in each progress callback of the
real pipeline), so a test can catch a job mid-decode without depending on how fast the machine is.
"""

from __future__ import annotations

import os
import signal
import threading
import time

import httpx
import pytest
import redis
from stack import flushed_redis, printed
from test_service_api import assert_error, make_settings, submit, wait_final

from fastmesh_jobs.runtime import wait_for
from service.processes import ServedApp, WorkerProcess

DB = int(os.environ.get("FASTMESH_TEST_REDIS_DB", "13"))
SLOW = "0.3"  # seconds per progress callback (~10 per job with the tiny model): jobs last seconds, not 0.1 s
DOOMED = "1.0"  # workers about to be killed: their jobs last long enough to be caught running on a busy machine


@pytest.fixture(scope="module")
def redis_url():
    with flushed_redis(DB) as url:
        yield url


class Env:
    """An app (own prefix and queue) and the workers started for it, all stopped by :meth:`close`."""

    def __init__(self, redis_url: str, weights: str, name: str, logs):
        self.s = make_settings(redis_url, name, weights=weights, max_attempts=2)
        self.app = ServedApp(self.s)
        self.name, self.logs = name, logs
        self.workers: list[WorkerProcess] = []

    def spawn(self, name: str, **extra) -> WorkerProcess:
        """Start a worker without waiting for it (its ~3 s of imports overlap the test's own waiting)."""
        w = WorkerProcess(self.s, f"{self.name[:30]}-{name}", self.logs / f"{name}.log", **extra)
        self.workers.append(w)
        return w

    def start(self, name: str, **extra) -> WorkerProcess:
        return self.spawn(name, **extra).wait_ready()

    def attempt(self, job_id: str) -> int:
        return int(redis.Redis.from_url(self.s.redis_url).hget(f"{self.s.redis_prefix}:job:{job_id}", "attempt"))

    def close(self) -> None:
        for w in self.workers:
            if w.proc.poll() is None:
                os.kill(w.pid, signal.SIGCONT)  # in case a test left it stopped
            w.stop()
        self.app.stop()


@pytest.fixture
def env(redis_url, weights, request, tmp_path):
    e = Env(redis_url, weights, request.node.name[:40], tmp_path)
    yield e
    e.close()


@pytest.fixture(scope="module")
def slow(redis_url, weights, tmp_path_factory):
    """One slow worker shared by the tests that only watch or cancel jobs."""
    e = Env(redis_url, weights, "slow", tmp_path_factory.mktemp("slow"))
    e.start("w", FASTMESH_DEBUG_STEP_DELAY=SLOW)
    yield e
    e.close()


def job(app, job_id):
    return httpx.get(f"{app.url}/v1/jobs/{job_id}").json()


def wait_running(app, job_id):
    return wait_for(lambda: (j := job(app, job_id))["status"] == "running" and j, 30, 0.02,
                    what=f"job {job_id} to run")


def wait_status(app, job_id, status, timeout=15):
    return wait_for(lambda: (j := job(app, job_id))["status"] == status and j, timeout, 0.02,
                    what=f"job {job_id} to be {status}")


def test_pipeline_loaded_once_per_process(env):
    w = env.start("w")
    ids = [submit(env.app.url, max_vertices=10, seed=i).json()["id"] for i in range(3)]
    for i in ids:
        assert wait_final(env.app.url, i)["status"] == "succeeded"
    key = f"{env.s.redis_prefix}:worker:{w.name}"
    info = wait_for(lambda: (inf := redis.Redis.from_url(env.s.redis_url).hgetall(key)) and inf[b"jobs"] == b"3"
                    and inf, 10, what="worker info to count 3 jobs")
    assert info[b"loads"] == b"1", info  # three jobs, one model load
    assert info[b"pid"] == str(w.pid).encode()
    assert w.log().count("pipeline loaded") == 1


def test_progress_moves_while_decoding(slow):
    app = slow.app
    job_id = submit(app.url, max_vertices=64).json()["id"]
    seen: list[tuple[str, float]] = []

    def moved():
        j = job(app, job_id)
        p = (j["progress"]["stage"], j["progress"]["fraction"])
        if j["status"] == "running" and (not seen or seen[-1] != p):
            seen.append(p)
        return len(seen) >= 4 or j["status"] != "running" and seen

    wait_for(moved, 60, 0.05, what="progress to move")
    assert len(seen) >= 4, seen
    assert "vertices" in [s for s, _ in seen]
    fractions = [f for _, f in seen]
    assert fractions == sorted(fractions) and 0 <= fractions[0] < fractions[-1] <= 1, seen
    httpx.delete(f"{app.url}/v1/jobs/{job_id}")
    wait_status(app, job_id, "cancelled")


def test_cancel_running_job_frees_the_worker(slow):
    app, s, w = slow.app, slow.s, slow.workers[0]
    victim = submit(app.url, max_vertices=64).json()["id"]
    wait_running(app, victim)
    r = httpx.delete(f"{app.url}/v1/jobs/{victim}")
    assert r.status_code == 200 and r.json()["status"] == "cancelled"
    assert_error(httpx.get(f"{app.url}/v1/jobs/{victim}/result"), 409, "job_cancelled")
    nxt = submit(app.url, max_vertices=5).json()["id"]
    assert wait_final(app.url, nxt, timeout=30)["status"] == "succeeded"
    assert job(app, victim)["status"] == "cancelled"
    assert f"job {victim} attempt 1 stopped (cancelled or superseded)" in w.log()  # stopped, not run to the end
    client = redis.Redis.from_url(s.redis_url)
    assert client.scard(f"{s.redis_prefix}:running") == 0
    assert not client.exists(f"{s.redis_prefix}:result:{victim}:glb")


def test_cancel_queued_job_never_runs(slow):
    app, w = slow.app, slow.workers[0]
    first = submit(app.url, max_vertices=12).json()["id"]
    wait_running(app, first)
    os.kill(w.pid, signal.SIGSTOP)  # hold the worker so the next job stays queued
    try:
        queued = submit(app.url, max_vertices=5).json()["id"]
        assert job(app, queued)["status"] == "queued"
        assert httpx.delete(f"{app.url}/v1/jobs/{queued}").json()["status"] == "cancelled"
    finally:
        os.kill(w.pid, signal.SIGCONT)
    assert wait_final(app.url, first, timeout=30)["status"] == "succeeded"
    time.sleep(0.3)
    assert job(app, queued)["status"] == "cancelled" and job(app, queued)["started_at"] is None
    assert slow.s.redis_prefix and redis.Redis.from_url(slow.s.redis_url).llen(f"rq:queue:{slow.s.queue_name}") == 0


def test_sigkill_mid_job_is_retried_on_another_worker(env):
    app, s = env.app, env.s
    doomed = env.start("doomed", FASTMESH_DEBUG_STEP_DELAY=DOOMED)
    job_id = submit(app.url, max_vertices=20).json()["id"]
    wait_running(app, job_id)
    rescuer = env.spawn("rescuer")  # starts up while the doomed worker runs the job
    doomed.proc.send_signal(signal.SIGKILL)
    doomed.proc.wait()
    # The reaper (in the API, and in live workers) sees the heartbeat expire and queues attempt 2.
    wait_for(lambda: env.attempt(job_id) == 2, 15, 0.02, what="requeue after SIGKILL")
    final = wait_final(app.url, job_id)
    assert final["status"] == "succeeded" and final["error"] is None, final
    assert env.attempt(job_id) == 2
    wait_for(lambda: f"{job_id} succeeded" in rescuer.log(), 10, what="the rescuer's log line")  # logged after storing
    client = redis.Redis.from_url(s.redis_url)
    assert int(client.hget(f"{s.redis_prefix}:stats:jobs", "retried")) == 1
    assert 'fastmesh_jobs_total{status="retried"} 1.0' in httpx.get(f"{app.url}/metrics").text


def test_sigkill_on_every_attempt_fails_clearly(env):
    app = env.app
    first = env.start("doomed1", FASTMESH_DEBUG_STEP_DELAY=DOOMED)
    job_id = submit(app.url, max_vertices=20).json()["id"]
    wait_running(app, job_id)
    second = env.spawn("doomed2", FASTMESH_DEBUG_STEP_DELAY=DOOMED)
    second.wait_ready()
    first.proc.send_signal(signal.SIGKILL)
    first.proc.wait()
    wait_for(lambda: env.attempt(job_id) == 2 and job(app, job_id)["status"] == "running", 15, 0.02,
             what="attempt 2 to run")
    second.proc.send_signal(signal.SIGKILL)  # max_attempts = 2
    second.proc.wait()
    final = wait_final(app.url, job_id, timeout=15)
    assert final["status"] == "failed", final
    assert final["error"]["code"] == "worker_lost" and "2 attempt" in final["error"]["message"]
    assert final["finished_at"] is not None
    assert_error(httpx.get(f"{app.url}/v1/jobs/{job_id}/result"), 409, "job_failed")


def test_a_worker_killed_mid_job_comes_back_under_its_own_name(env):
    """As systemd, compose or Kubernetes restart it: same --name right after kill -9.  RQ keeps the dead
    worker's registration for minutes; its stale heartbeat says it is dead, so the new one takes the name,
    runs the requeued job, and a second live worker of that name is still refused."""
    app = env.app
    doomed = env.start("same", FASTMESH_DEBUG_STEP_DELAY=DOOMED)
    job_id = submit(app.url, max_vertices=20).json()["id"]
    wait_running(app, job_id)
    doomed.proc.send_signal(signal.SIGKILL)
    doomed.proc.wait()
    again = env.start("same")  # the same name
    assert again.name == doomed.name
    final = wait_final(app.url, job_id, timeout=30)
    assert final["status"] == "succeeded", final
    assert "clearing the registration of a dead worker" in again.log()
    twin = env.spawn("same")
    assert twin.proc.wait(30) == 1
    assert "is alive" in twin.log()
    assert again.proc.poll() is None


def test_job_timeout(env):
    env.start("w", FASTMESH_DEBUG_STEP_DELAY=SLOW, FASTMESH_JOB_TIMEOUT="0.5")
    final = wait_final(env.app.url, submit(env.app.url, max_vertices=64).json()["id"], timeout=20)
    assert final["status"] == "failed" and final["error"]["code"] == "timeout", final
    assert "0.5 s" in final["error"]["message"]


def test_hung_job_with_a_live_worker_is_failed_by_the_reaper(env, caplog):
    """A decoder stuck in one call (here: an 8 s sleep) never reaches its own timeout check; its heartbeat
    thread keeps beating, so the job is not "lost" either: the reaper fails it as overdue.  The timeout leaves
    the steps before the first progress report (the closed decision) time to reach the sleep under load."""
    w = env.start("hung", FASTMESH_DEBUG_STEP_DELAY="12", FASTMESH_JOB_TIMEOUT="2")
    job_id = submit(env.app.url, max_vertices=20).json()["id"]
    final = wait_final(env.app.url, job_id, timeout=30)
    assert final["status"] == "failed" and final["error"]["code"] == "timeout", final
    w.proc.send_signal(signal.SIGKILL)  # rather than waiting out its sleep
    w.proc.wait()
    assert f"reaper: job {job_id} timeout" in caplog.text + w.log()
    assert env.attempt(job_id) == 1


def test_sigterm_hands_the_running_job_back(env):
    app = env.app
    w = env.start("leaving", FASTMESH_DEBUG_STEP_DELAY=DOOMED)
    job_id = submit(app.url, max_vertices=64).json()["id"]
    wait_running(app, job_id)
    nxt = env.spawn("next")
    w.proc.send_signal(signal.SIGTERM)
    assert w.proc.wait(20) == 0  # warm shutdown stops the decoder instead of waiting for the job
    assert f"job {job_id} handed back to the queue" in w.log()
    assert env.attempt(job_id) == 2
    assert wait_final(app.url, job_id)["status"] == "succeeded"  # finished by the next worker
    # The worker logs the success after storing it: under load the line can trail the status.
    wait_for(lambda: f"{job_id} succeeded" in nxt.log(), 10, what="the next worker's log line")


def test_a_worker_stops_listening_at_once(redis_url):
    """The exit of a worker whose listener thread took its unsubscribe reply before being told to stop (the race a
    busy machine loses) does not wait for the listener's 60 s."""
    from worker.main import FastMeshWorker

    w = FastMeshWorker(["t-unsubscribe"], connection=redis.Redis.from_url(redis_url), name=f"t-unsub-{os.getpid()}")
    w.subscribe()
    wait_for(lambda: w.pubsub.subscribed, 10, what="the subscription")
    w.pubsub.unsubscribe()  # the reply reaches the listener, which then waits for a subscription
    wait_for(lambda: not w.pubsub.subscribed, 10, what="the unsubscribe reply")
    time.sleep(0.2)
    leaving = threading.Thread(target=w.unsubscribe, daemon=True)
    leaving.start()
    leaving.join(10)
    assert not leaving.is_alive(), "the worker's unsubscribe waits for its listener"


def test_jobs_queued_under_the_former_function_name_still_run():
    import worker.jobs
    import worker.tasks

    assert worker.tasks.run_job is worker.jobs.run_job


# A worker's GPU failing mid-job.  The hook below makes a worker's pipeline raise what torch raises after a
# device-side assert, for the jobs of one seed; having raised, it fails every later job of that process, as a
# CUDA context poisoned by the assert does.  With ONCE set (a file), only the first such job anywhere raises:
# a fault of one process that another worker does not meet.
DEVICE_HOOK = '''
import os

import fastmesh.pipeline as pipeline

_generate, _poisoned = pipeline.Pipeline.generate, []


def generate(self, shape, params=None, **kwargs):
    once = os.environ.get("FMTEST_DEVICE_ERROR_ONCE")
    hit = params is not None and params.seed == int(os.environ["FMTEST_DEVICE_ERROR_SEED"])
    if _poisoned or (hit and not (once and os.path.exists(once))):
        if once:
            open(once, "w").close()
        _poisoned.append(True)
        raise RuntimeError("CUDA error: device-side assert triggered\\nCUDA kernel errors might be asynchronously "
                           "reported at some other API call, so the stacktrace below might be incorrect.")
    return _generate(self, shape, params, **kwargs)


pipeline.Pipeline.generate = generate
'''
BAD_SEED = 4242


def device_hook(tmp_path, once: bool = False) -> dict[str, str]:
    """Worker environment that loads :data:`DEVICE_HOOK` at start-up (as ``sitecustomize``)."""
    (tmp_path / "hook").mkdir(exist_ok=True)
    (tmp_path / "hook" / "sitecustomize.py").write_text(DEVICE_HOOK)
    env = {"PYTHONPATH": os.pathsep.join(filter(None, [str(tmp_path / "hook"), os.environ.get("PYTHONPATH")])),
           "FMTEST_DEVICE_ERROR_SEED": str(BAD_SEED)}
    if once:
        env["FMTEST_DEVICE_ERROR_ONCE"] = str(tmp_path / "raised-once")
    return env


def test_device_errors_are_told_apart():
    import torch

    from fastmesh.pipeline import GenerationError
    from worker.jobs import is_device_error

    assert is_device_error(RuntimeError("CUDA error: device-side assert triggered"))
    assert is_device_error(torch.AcceleratorError("CUDA error: an illegal memory access was encountered"))
    assert is_device_error(RuntimeError("CUBLAS_STATUS_EXECUTION_FAILED when calling `cublasSgemm( handle, ...)`"))
    try:
        try:
            raise RuntimeError("CUDA error: unspecified launch failure")
        except RuntimeError as inner:
            raise ValueError("while exporting") from inner
    except ValueError as outer:
        assert is_device_error(outer)
    assert not is_device_error(torch.OutOfMemoryError("CUDA out of memory. Tried to allocate 2.00 GiB"))
    assert not is_device_error(GenerationError("no_faces", "the face model connected no triangles"))
    assert not is_device_error(RuntimeError("shape mismatch"))
    assert not is_device_error(ValueError("max_vertices above the model's limit"))


def test_device_error_fails_the_job_after_two_workers_and_each_exits_for_a_restart(env, tmp_path):
    """The job that triggers the assert goes to another worker once, then fails ``device_error``; each worker
    that met the error leaves (status 3) without taking another job, and the job queued behind the failing
    one is done by a fresh worker, not failed by the poisoned one."""
    app, hook = env.app, device_hook(tmp_path)
    bad = submit(app.url, max_vertices=10, seed=BAD_SEED).json()["id"]
    good = submit(app.url, max_vertices=10, seed=1).json()["id"]  # queued behind it, ahead of its attempt 2
    first = env.spawn("gpu1", **hook)  # it may be gone before it is seen ready
    assert first.proc.wait(60) == 3, first.log()[-3000:]
    assert "device error" in first.log() and "exiting with status 3" in first.log()
    assert job(app, good)["status"] == "queued"  # the poisoned worker left it for another
    assert job(app, bad)["status"] == "queued" and env.attempt(bad) == 2
    second = env.spawn("gpu2", **hook)  # it may finish both jobs and leave before it is seen ready
    assert wait_final(app.url, good)["status"] == "succeeded"
    final = wait_final(app.url, bad)
    assert final["status"] == "failed" and final["error"]["code"] == "device_error", final
    assert "CUDA error: device-side assert triggered" in final["error"]["message"]
    assert "failed this way on another worker before" in final["error"]["message"]
    assert final["finished_at"] is not None
    assert second.proc.wait(60) == 3, second.log()[-3000:]
    store_job = redis.Redis.from_url(env.s.redis_url).hget(f"{env.s.redis_prefix}:job:{good}", "worker")
    assert store_job.decode() == second.name
    assert_error(httpx.get(f"{app.url}/v1/jobs/{bad}/result"), 409, "job_failed")
    client = redis.Redis.from_url(env.s.redis_url)
    assert client.scard(f"{env.s.redis_prefix}:running") == 0  # nothing left "running"


def test_device_error_of_one_process_is_retried_on_a_fresh_worker(env, tmp_path):
    """A fault that passes with the process: attempt 2, on a fresh worker, succeeds."""
    app, hook = env.app, device_hook(tmp_path, once=True)
    job_id = submit(app.url, max_vertices=10, seed=BAD_SEED).json()["id"]
    first = env.spawn("gpu1", **hook)
    assert first.proc.wait(60) == 3, first.log()[-3000:]
    env.spawn("gpu2", **hook)
    final = wait_final(app.url, job_id)
    assert final["status"] == "succeeded" and final["error"] is None, final
    assert env.attempt(job_id) == 2


def test_make_run_starts_a_fresh_worker_after_a_device_error(weights, tmp_path):
    """`make run` as the supervisor: its worker leaves after the GPU error (status 3), `make run` says why and
    starts another, which runs the job's second attempt."""
    import subprocess
    import sys

    from test_service_run import run_env

    from service.processes import free_port

    port = free_port()
    env = run_env(FASTMESH_PORT=str(port), FASTMESH_WEIGHTS=weights, **device_hook(tmp_path, once=True))
    proc = subprocess.Popen([sys.executable, "-m", "service.run"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, env=env)
    lines: list[str] = []

    try:
        wait_for(printed(proc, lines, "Ctrl-C stops everything"), 120, 0, what="the service to be ready")
        url = f"http://127.0.0.1:{port}"
        job_id = submit(url, max_vertices=10, seed=BAD_SEED).json()["id"]
        wait_for(printed(proc, lines, "exited with code 3 after a GPU error"), 60, 0, what="the restart message")
        final = wait_final(url, job_id, timeout=120)
        assert final["status"] == "succeeded", final
    finally:
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0, "".join(lines) + rest
    assert "starting it again" in "".join(lines)
