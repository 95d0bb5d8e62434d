"""Stage timings that add up: every second of a generation in exactly one named stage, ``filtering`` only the masked
re-predictions, the weighing of rivals its own stage; a job's ``total`` the sum of its stages, the queue apart."""

from __future__ import annotations

import time

import numpy as np
import pytest
import torch
import trimesh
from stack import make_settings

from fastmesh.params import GenerateParams
from fastmesh.pipeline import Pipeline
from fastmesh.request import TIMED_STAGES
from fastmesh.shapes.io import sample_surface
from fastmesh.shapes.shape import Shape
from fastmesh_jobs.blobs import shape_to_bytes

torch.set_num_threads(1)
SLACK = 0.03  # seconds outside any stage per call: argument checks before the clock starts, a batch's bookkeeping


@pytest.fixture(scope="module")
def pipe() -> Pipeline:
    return Pipeline.random(seed=0)


def _sphere() -> Shape:
    m = trimesh.creation.icosphere(3)
    return Shape(vertices=np.asarray(m.vertices) * 3.0 + 5.0, faces=np.asarray(m.faces))


def _points() -> Shape:
    pts, nrm = sample_surface(_sphere(), 2000, seed=0)
    return Shape(vertices=pts.astype(np.float64), normals=nrm.astype(np.float64))


@pytest.mark.parametrize("kind", ["mesh", "points"])
@pytest.mark.parametrize("filtering", [False, True])
def test_the_stages_add_up_to_the_call(pipe, kind, filtering):
    shape = _sphere() if kind == "mesh" else _points()
    t = time.perf_counter()
    res = pipe.generate(shape, GenerateParams(seed=1, max_vertices=32, candidates=2, filtering=filtering))
    wall = time.perf_counter() - t
    assert set(res.timings) == set(TIMED_STAGES)
    assert sum(res.timings.values()) == pytest.approx(wall, abs=SLACK)
    assert all(v >= 0 for v in res.timings.values())
    assert res.timings["vertices"] > 0 and res.timings["faces"] > 0
    assert res.timings["weighing"] > 0  # two candidates weighed: not filtering's
    assert (res.timings["filtering"] > 0) == filtering


def test_an_unrun_request_is_counted_too(pipe):
    """A box rebuilt from its planes runs no network: its seconds are the encode and face stages'."""
    box = trimesh.creation.box(extents=(1.0, 2.0, 0.5))
    shape = Shape(vertices=np.asarray(box.vertices), faces=np.asarray(box.faces))
    t = time.perf_counter()
    res = pipe.generate(shape, GenerateParams(target_faces=40))
    wall = time.perf_counter() - t
    assert res.tokens == 0 and sum(res.timings.values()) == pytest.approx(wall, abs=SLACK)
    assert res.timings["vertices"] == res.timings["filtering"] == res.timings["weighing"] == 0.0


def test_a_batched_jobs_stages_add_up_to_its_time_in_the_batch(pipe):
    """In a batch a job waits for the round's other jobs (their encoding before the shared decoding, their faces
    after it): that wait is its ``vertices``, so its stages still add up to its time from start to end."""
    from fastmesh.batch import Batch

    jobs = [(_sphere() if i % 2 else _points(), GenerateParams(seed=i, max_vertices=32, candidates=2))
            for i in range(3)]
    batch, start, end = Batch(pipe), {}, {}

    def progress(i):
        return lambda stage, fraction: end.__setitem__(i, time.perf_counter())

    for i, (shape, params) in enumerate(jobs):
        start[i] = time.perf_counter()
        batch.add(i, pipe.steps(shape, params, progress=progress(i)))
    while len(batch):
        batch.round()
    done = batch.pop_done()
    assert sorted(done) == [0, 1, 2]
    for i, res in done.items():
        assert sum(res.timings.values()) == pytest.approx(end[i] - start[i], abs=SLACK), (i, res.timings)


@pytest.fixture
def worker_state(redis_url, pipe):
    """The worker's module state with this test's store and the tiny pipeline (no process, no model load)."""
    from fastmesh_jobs.store import Store
    from worker.jobs import STATE

    settings = make_settings(redis_url, "timings")
    saved = (STATE.settings, STATE.store, STATE.pipeline)
    STATE.configure(settings, Store(settings))
    STATE.pipeline = pipe
    yield STATE
    STATE.settings, STATE.store, STATE.pipeline = saved


def test_a_jobs_total_is_its_stages_and_the_queue_is_apart(worker_state):
    from worker.jobs import run_job

    store = worker_state.store
    params = {"seed": 1, "max_vertices": 32, "formats": ["glb"]}
    job_id = store.create("tester", params, {"filename": "ball.ply", "kind": "mesh"}, shape_to_bytes(_sphere()), 0.04)
    time.sleep(0.5)  # queued
    run_job(job_id, 1)
    job = store.public(store.get(job_id))
    assert job["status"] == "succeeded", job["error"]
    t = job["timings"]
    stages = {k: v for k, v in t.items() if k not in ("queue", "total")}
    assert set(stages) == {"load", *TIMED_STAGES, "export"} and all(v is not None for v in stages.values())
    assert sum(stages.values()) == pytest.approx(t["total"], abs=0.05)
    assert t["queue"] >= 0.5  # the queue is reported apart ...
    ran = store.get(job_id)
    assert t["total"] == pytest.approx(0.04 + ran["finished_at"] - ran["started_at"], abs=1e-6)  # ... and not in total
