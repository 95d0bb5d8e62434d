"""``fastmesh-worker`` with ``FASTMESH_MAX_BATCH`` > 1 (``worker.batch``): queued jobs run together, each as it
runs alone, with the one-at-a-time worker's job life (cancel, warm shutdown, death, GPU errors)."""

from __future__ import annotations

import os
import signal
from datetime import datetime

import httpx
import numpy as np
import pytest
import redis
from stack import flushed_redis
from test_service_api import sphere_xyz, submit, wait_final
from test_worker import DB, DOOMED, SLOW, Env, job, wait_running

from fastmesh.params import GenerateParams
from fastmesh.pipeline import Pipeline
from fastmesh.shapes.io import with_normals
from fastmesh_jobs.blobs import mesh_from_bytes, shape_from_bytes
from fastmesh_jobs.runtime import wait_for

BATCH = {"FASTMESH_MAX_BATCH": "4"}


@pytest.fixture(scope="module")
def redis_url():
    with flushed_redis(DB) as url:
        yield url


@pytest.fixture
def env(redis_url, weights, request, tmp_path):
    e = Env(redis_url, weights, "b-" + request.node.name[:38], tmp_path)
    yield e
    e.close()


def _stored(env, key: str) -> bytes:
    return redis.Redis.from_url(env.s.redis_url).get(f"{env.s.redis_prefix}:{key}")


def _hash(env, job_id: str, field: str) -> str | None:
    v = redis.Redis.from_url(env.s.redis_url).hget(f"{env.s.redis_prefix}:job:{job_id}", field)
    return None if v is None else v.decode()


def test_queued_jobs_run_together_and_each_gives_what_it_gives_alone(env, weights):
    asked = [dict(seed=1, max_vertices=20), dict(seed=2, max_vertices=20), dict(seed=3, max_vertices=20, candidates=1),
             dict(seed=4, max_vertices=16, temperature=0.7)]
    ids = [submit(env.app.url, sphere_xyz(seed=i), **p).json()["id"] for i, p in enumerate(asked)]
    w = env.start("b", **BATCH)  # all four are queued: it takes them at once
    finals = [wait_final(env.app.url, i) for i in ids]
    assert [f["status"] for f in finals] == ["succeeded"] * 4, finals
    started = max(datetime.fromisoformat(f["started_at"]) for f in finals)
    assert started < min(datetime.fromisoformat(f["finished_at"]) for f in finals)  # all four ran at once
    pipe = Pipeline.from_pretrained(weights)
    for job_id, p, final in zip(ids, asked, finals, strict=True):
        alone = pipe.generate(with_normals(shape_from_bytes(_stored(env, f"input:{job_id}"))), GenerateParams(**p))
        vertices, faces = mesh_from_bytes(_stored(env, f"result:{job_id}:npz"))
        assert np.array_equal(vertices, alone.vertices) and np.array_equal(faces, alone.faces)
        assert final["result"]["seed"] == alone.info["chosen_seed"] and final["timings"]["vertices"] > 0
    info = redis.Redis.from_url(env.s.redis_url).hget(f"{env.s.redis_prefix}:worker:{w.name}", "max_batch")
    assert info == b"4"


def test_a_cancelled_job_leaves_its_batch_and_sigterm_hands_the_rest_back(env):
    w = env.start("b", FASTMESH_DEBUG_STEP_DELAY=SLOW, **BATCH)

    def running_together(n):
        ids = [submit(env.app.url, max_vertices=64, seed=i).json()["id"] for i in range(n)]
        for i in ids:
            wait_running(env.app, i)
        return ids

    ids = running_together(3)
    assert httpx.delete(f"{env.app.url}/v1/jobs/{ids[0]}").json()["status"] == "cancelled"
    for i in ids[1:]:  # the others go on
        assert wait_final(env.app.url, i)["status"] == "succeeded"
    assert f"job {ids[0]} attempt 1 stopped (cancelled or superseded)" in w.log()
    assert job(env.app, ids[0])["status"] == "cancelled"
    ids = running_together(3)
    nxt = env.spawn("next")  # one job at a time
    w.proc.send_signal(signal.SIGTERM)
    assert w.proc.wait(30) == 0, w.log()[-3000:]
    for i in ids:
        assert f"job {i} handed back to the queue" in w.log()
        assert env.attempt(i) == 2
        assert wait_final(env.app.url, i)["status"] == "succeeded"
    wait_for(lambda: all(f"{i} succeeded" in nxt.log() for i in ids), 10, what="the next worker's log lines")


def test_a_batched_worker_killed_mid_batch_loses_no_job(env):
    doomed = env.start("doomed", FASTMESH_DEBUG_STEP_DELAY=DOOMED, **BATCH)
    ids = [submit(env.app.url, max_vertices=20, seed=i).json()["id"] for i in range(3)]
    for i in ids:
        wait_running(env.app, i)
    env.spawn("rescuer", **BATCH)
    doomed.proc.send_signal(signal.SIGKILL)
    doomed.proc.wait()
    for i in ids:
        assert wait_final(env.app.url, i)["status"] == "succeeded"
        assert env.attempt(i) == 2
    client = redis.Redis.from_url(env.s.redis_url)
    assert client.scard(f"{env.s.redis_prefix}:running") == 0 and client.llen(f"rq:queue:{env.s.queue_name}") == 0


# A GPU failing in a batch: the hook makes Pipeline.steps raise what torch raises after a device-side assert for
# the jobs of one seed, and for every job after it in that process (a poisoned CUDA context).
STEPS_HOOK = '''
import os

import fastmesh.pipeline as pipeline

_steps, _poisoned = pipeline.Pipeline.steps, []


def steps(self, shape, params=None, *args, **kwargs):
    if _poisoned or (params is not None and params.seed == int(os.environ["FMTEST_DEVICE_ERROR_SEED"])):
        _poisoned.append(True)
        raise RuntimeError("CUDA error: device-side assert triggered")
    return (yield from _steps(self, shape, params, *args, **kwargs))


pipeline.Pipeline.steps = steps
'''
BAD_SEED = 4242


def test_a_gpu_error_in_a_batch_hands_every_job_on_and_the_worker_exits(env, tmp_path):
    """The job that met the error gets one more attempt elsewhere (``device_errors`` 1), the job running beside
    it goes back to the queue unblamed, the one still queued stays there; the worker exits with status 3 and a
    fresh worker runs all three."""
    (tmp_path / "hook").mkdir()
    (tmp_path / "hook" / "sitecustomize.py").write_text(STEPS_HOOK)
    hook = {"PYTHONPATH": os.pathsep.join(filter(None, [str(tmp_path / "hook"), os.environ.get("PYTHONPATH")])),
            "FMTEST_DEVICE_ERROR_SEED": str(BAD_SEED)}
    beside, bad, queued = (submit(env.app.url, max_vertices=10, seed=s).json()["id"] for s in (1, BAD_SEED, 2))
    gpu = env.spawn("gpu", **BATCH, **hook)
    assert gpu.proc.wait(60) == 3, gpu.log()[-3000:]
    assert "exiting with status 3" in gpu.log()
    assert job(env.app, bad)["status"] == "queued" and _hash(env, bad, "device_errors") == "1"
    assert job(env.app, beside)["status"] == "queued" and env.attempt(beside) == 2
    assert _hash(env, beside, "device_errors") is None
    assert job(env.app, queued)["status"] == "queued" and env.attempt(queued) == 1
    env.spawn("fresh", **BATCH)
    for i in (beside, bad, queued):
        assert wait_final(env.app.url, i)["status"] == "succeeded"
