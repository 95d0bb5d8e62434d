"""Bounded memory for every request: uploads, ``input.ply`` and previews are worked on in capped child
processes, the prechecks count what parsers would expand, and the limits cannot be turned against others."""

from __future__ import annotations

import os
import threading
import time

import httpx
import pytest
import stack
from hostile import (
    allocate,
    die,
    gltf_empty_nodes,
    heavy_obj,
    obj_unspaced_faces,
    off_one_vertex_faces,
    ply_fans,
    returns_an_object,
    sleep_for,
    strided_accessor_glb,
)
from stack import assert_error, make_settings, sphere_points, xyz_bytes

import fastmesh.shapes.gltf_check
import fastmesh.shapes.io
from fastmesh.shapes.io import load_shape
from fastmesh.shapes.shape import ShapeError
from fastmesh_jobs.runtime import wait_for
from service.children import CappedPool, ChildFailed
from service.processes import ServedApp

MIB = 1024 * 1024


def rss() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


class PeakRss:
    """The most this process's resident memory rose above its start while the block ran (sampled)."""

    def __enter__(self):
        self.start, self.peak, self._stop = rss(), 0, threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()
        return self

    def _sample(self):
        while not self._stop.is_set():
            self.peak = max(self.peak, rss() - self.start)
            time.sleep(0.01)

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()


def post(url: str, name: str, data: bytes, headers=None, **fields) -> httpx.Response:
    return stack.post(url, name, data, headers, timeout=120, **fields)  # big uploads: a longer wait


@pytest.fixture(scope="module")
def open_api(redis_url):
    app = ServedApp(make_settings(redis_url, "mem", max_queue_depth=10_000))
    yield app
    app.stop()


# ---------------------------------------------------------------------------------------- the capped children


def test_a_child_past_its_cap_its_deadline_or_dead_fails_alone():
    pool = CappedPool(1, 768 * MIB, name="fastmesh-test-cap")
    try:
        assert pool.call(allocate, None, 50, timeout=60) == 50 * MIB
        for fn, args, reason in ((allocate, (2000,), "memory"), (sleep_for, (30,), "deadline"), (die, (), "crashed")):
            t0 = time.monotonic()
            with pytest.raises(ChildFailed) as e:
                pool.call(fn, None, *args, timeout=3)
            assert e.value.reason == reason and time.monotonic() - t0 < 10
            assert pool.call(allocate, None, 10, timeout=60) == 10 * MIB  # a fresh child serves the next task
    finally:
        pool.close()


def test_an_upload_needing_more_than_the_cap_is_413_and_the_api_does_not_grow(redis_url):
    """The parse of a 9 MB OBJ takes ~200 MB: over a 400 MiB child (~330 MiB of it its imports) it is refused
    (the parser's MemoryError, or the child's death), and the API process (this one, serving in a thread) holds
    only the upload meanwhile."""
    app = ServedApp(make_settings(redis_url, "memcap", child_memory_mb=400, max_queue_depth=10_000))
    try:
        post(app.url, "warm.xyz", xyz_bytes(sphere_points(50)))  # the child is started and imported
        data = heavy_obj()
        with PeakRss() as peak:
            r = post(app.url, "heavy.obj", data)
        assert_error(r, 413, "too_large")
        assert peak.peak < 100 * MIB, peak.peak / MIB
        assert post(app.url, "after.xyz", xyz_bytes(sphere_points(50))).status_code == 202
    finally:
        app.stop()


def test_input_ply_is_sampled_outside_the_api_process(open_api):
    """20 concurrent overlays of 200,000 points of a 327,680-face input: the API grows by their answers only, and
    the requests share the samples made while they wait."""
    import trimesh

    mesh = trimesh.creation.icosphere(7)  # 327,680 faces
    r = post(open_api.url, "dense.ply", mesh.export(file_type="ply"))
    assert r.status_code == 202, r.text
    url = f"{open_api.url}/v1/jobs/{r.json()['id']}/input.ply?points=200000"
    httpx.get(url, timeout=60)
    got: list[httpx.Response] = []
    before = open_api.app.state.previews.samples
    with PeakRss() as peak:
        threads = [threading.Thread(target=lambda: got.append(httpx.get(url, timeout=120))) for _ in range(20)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    assert [g.status_code for g in got] == [200] * 20
    assert got[0].content == got[-1].content
    assert open_api.app.state.previews.samples - before <= 5
    assert peak.peak < 150 * MIB, peak.peak / MIB


# ---------------------------------------------------------------------------------------- prechecks


@pytest.fixture
def no_parser(monkeypatch):
    """The parser must not be reached: the precheck refuses first."""
    def refuse(*_):
        raise AssertionError("the parser ran")

    monkeypatch.setattr(fastmesh.shapes.io, "_load_trimesh", refuse)


def test_glb_accessors_with_a_one_byte_stride_are_refused(no_parser):
    with pytest.raises(ShapeError) as e:
        load_shape(strided_accessor_glb(64 * 1024, 4), filename="a.glb")
    assert "byteStride" in e.value.message


def test_glb_unused_accessor_bytes_count_against_the_limits(no_parser):
    with pytest.raises(ShapeError) as e:
        load_shape(strided_accessor_glb(1 << 20, 16, stride=64), filename="a.glb", max_points=10_000, max_faces=10_000)
    assert e.value.code == "too_large" and "accessors" in e.value.message


def test_the_16_accessor_glb_is_refused_over_http(open_api):
    assert_error(post(open_api.url, "amp.glb", strided_accessor_glb()), (413, 422))


def test_obj_faces_without_a_space_are_counted(no_parser):
    with pytest.raises(ShapeError) as e:
        load_shape(obj_unspaced_faces(2000), filename="a.obj", max_faces=1000)
    assert e.value.code == "too_large"


def test_obj_polygons_are_counted_as_triangles(no_parser):
    corners = " ".join(str(i + 1) for i in range(255))
    data = "".join(f"v {i} {i * i % 7} 0\n" for i in range(255)).encode() + f"f {corners}\n".encode() * 10
    with pytest.raises(ShapeError) as e:
        load_shape(data, filename="fan.obj", max_faces=2000)  # 10 faces, 2,530 triangles
    assert e.value.code == "too_large" and "2530 triangles" in e.value.message


def test_a_gltf_of_many_empty_objects_is_refused_before_it_is_parsed(monkeypatch):
    def refuse(*_):
        raise AssertionError("the JSON was parsed")

    monkeypatch.setattr(fastmesh.shapes.gltf_check.json, "loads", refuse)
    with pytest.raises(ShapeError) as e:
        load_shape(gltf_empty_nodes(600_000), filename="j.gltf")
    assert e.value.code == "too_large" and "JSON" in e.value.message


def test_ply_faces_are_counted_as_triangles(no_parser):
    with pytest.raises(ShapeError) as e:
        load_shape(ply_fans(100), filename="fan.ply", max_faces=10_000)  # 100 faces, 25,300 triangles
    assert e.value.code == "too_large" and "25300 triangles" in e.value.message


def test_off_counts_are_checked_before_parsing(no_parser):
    with pytest.raises(ShapeError) as e:
        load_shape(off_one_vertex_faces(2000), filename="a.off", max_faces=1000)
    assert e.value.code == "too_large"


def test_files_within_the_limits_still_load():
    assert len(load_shape(ply_fans(2, 5), filename="fan.ply", max_faces=6).faces) == 6  # two pentagons
    with pytest.raises(ShapeError, match="6 triangles"):
        load_shape(ply_fans(2, 5), filename="fan.ply", max_faces=5)
    assert len(load_shape(obj_unspaced_faces(3), filename="a.obj", normals=False).faces) >= 1


def test_normal_estimation_takes_memory_in_blocks():
    """The worker estimates a large cloud's normals: the neighbourhoods of 200,000 points at once took ~170 MB
    (N x k x 3 float64, twice, and the covariances); in blocks the peak is the tree and the answer."""
    import tracemalloc

    import numpy as np

    from fastmesh.shapes.io import estimate_normals

    points = np.random.default_rng(0).normal(size=(200_000, 3))
    tracemalloc.start()
    try:
        normals = estimate_normals(points)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert normals.shape == points.shape and np.allclose(np.linalg.norm(normals, axis=1), 1)
    assert peak < 60 * MIB, peak / MIB


def test_a_child_may_answer_plain_data_only():
    pool = CappedPool(1, 768 * MIB, name="fastmesh-test-plain")
    try:
        with pytest.raises(ChildFailed, match="only plain data"):
            pool.call(returns_an_object, None, timeout=60)
        assert pool.call(allocate, None, 1, timeout=60) == MIB
    finally:
        pool.close()


def test_warm_starts_every_child_and_close_stops_them():
    pool = CappedPool(2, 768 * MIB, name="fastmesh-test-warm")
    try:
        pool.warm()
        assert len(pool.pids()) == 2 and pool.started == 2
        assert pool.call(allocate, None, 1, timeout=60) == MIB and pool.started == 2  # a warm child served it
    finally:
        pool.close()
    assert pool.pids() == []


def test_the_app_starts_its_parse_and_render_processes_with_it(redis_url):
    """The first upload, preview or input.ply does not wait for a process to start and import its libraries."""
    from fastapi.testclient import TestClient

    from service.app import create_app

    app = create_app(make_settings(redis_url, "warmapp"))
    pools = (app.state.parses, app.state.renders.pool)
    with TestClient(app):  # no request: only the app's start
        for pool in pools:
            wait_for(lambda pool=pool: pool.started == pool.workers, 60, what=f"{pool.name} started")


# ---------------------------------------------------------------------------------------- the worker's memory


def test_a_large_cloud_is_thinned_before_the_pipeline_alike_through_every_interface():
    """A 200,000-point cloud is read as CLOUD_POINTS of its points, its normals estimated on those: by
    ``load_shape`` (the CLI, the Python API) and by the worker from the input the API stored whole."""
    import io

    import numpy as np

    from fastmesh.shapes.io import CLOUD_POINTS, ready_cloud, thinned
    from fastmesh_jobs.blobs import shape_from_bytes
    from service.parsing import parse_upload

    p = np.random.default_rng(0).normal(size=(200_000, 3))
    buf = io.BytesIO()
    np.save(buf, p / np.linalg.norm(p, axis=1, keepdims=True) * [1.0, 0.7, 0.4])
    shape = load_shape(buf.getvalue(), filename="cloud.npy")
    assert shape.vertices.shape == shape.normals.shape == (CLOUD_POINTS, 3)
    info, blob = parse_upload(buf.getvalue(), "cloud.npy", 500_000, 1_000_000)
    assert info["points"] == 200_000  # the job reports the upload as it is
    worker = ready_cloud(shape_from_bytes(blob))
    assert np.array_equal(worker.vertices, shape.vertices) and np.array_equal(worker.normals, shape.normals)
    small = shape_from_bytes(blob)
    small.vertices = small.vertices[:1000]
    assert thinned(small) is small


GIVE_BACK = """
import gc
from worker.jobs import give_back_memory
from fastmesh_jobs.memory import tune_malloc

def rss():
    return int(open("/proc/self/statm").read().split()[1]) * 4096 // 2**20

tune_malloc(arenas=None)
gc.disable()  # a job's cycles wait for the collector
kept, freed = [], []
for i in range(3000):  # 300 MB in blocks under the mmap threshold, every 50th kept: the heap cannot shrink
    (kept if i % 50 == 0 else freed).append(bytearray(100_000))
cycle = [freed]
cycle.append(cycle)
del freed, cycle
before = rss()
give_back_memory()
print(before, rss())
"""


def test_the_worker_hands_a_jobs_memory_back():
    """What a job freed (reference cycles included) goes back to the system between jobs, even where blocks still
    in use sit above it in the heap."""
    import subprocess
    import sys

    run = subprocess.run([sys.executable, "-c", GIVE_BACK], capture_output=True, timeout=120, text=True)
    assert run.returncode == 0, run.stderr[-2000:]
    before, after = map(int, run.stdout.split())
    assert before > 250 and after < before - 200, (before, after)
