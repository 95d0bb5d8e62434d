"""``fastmesh.remote.client`` and ``fastmesh submit`` against a served API with a real worker."""

from __future__ import annotations

import io
import os
import subprocess
import sys
from pathlib import Path

import httpx
import pytest
import redis
import trimesh
from test_service_api import make_settings, sphere_xyz

from fastmesh.remote.client import Client, JobFailed, ServiceError
from service.processes import ServedApp, WorkerProcess, free_port, local_redis

DB = int(os.environ.get("FASTMESH_TEST_REDIS_DB", "13"))


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    from fastmesh.pipeline import Pipeline

    url, server = local_redis(DB)
    client = redis.Redis.from_url(url)
    client.flushdb()
    weights = tmp_path_factory.mktemp("weights")
    Pipeline.random("tiny", seed=0).save(str(weights))
    s = make_settings(url, "client", weights=str(weights), api_keys=["sekrit"])
    app = ServedApp(s)
    worker = WorkerProcess(s, "client-w", tmp_path_factory.mktemp("logs") / "w.log").wait_ready()
    yield app
    worker.stop()
    app.stop()
    client.flushdb()
    if server:
        server.stop()


@pytest.fixture
def sphere(tmp_path) -> Path:
    p = tmp_path / "ball.xyz"
    p.write_bytes(sphere_xyz())
    return p


def test_client_submit_wait_download(served, sphere, tmp_path):
    seen = []
    with Client(served.url, api_key="sekrit") as c:
        job = c.submit(sphere, seed=1, max_vertices=12, formats="glb", enhancer=False)
        assert job["status"] in ("queued", "running") and job["params"]["enhancer"] is False
        done = c.wait(job["id"], progress=lambda j: seen.append(j["status"]), timeout=60)
        assert done["status"] == "succeeded" and seen[-1] == "succeeded"
        out = tmp_path / "ball.obj"
        c.download(job["id"], out)
        mesh = trimesh.load(out, process=False)
        assert len(mesh.faces) == done["result"]["faces"]
        assert c.cancel(job["id"]) is None  # finished: deleted
        with pytest.raises(ServiceError) as e:
            c.job(job["id"])
        assert e.value.status == 404 and e.value.code == "not_found"


def test_client_errors(served, tmp_path):
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"not a ply at all")
    with Client(served.url, api_key="sekrit") as c, pytest.raises(ServiceError) as e:
        c.submit(bad)
    assert e.value.status == 422 and e.value.code == "unreadable"
    with Client(served.url, api_key="wrong") as c, pytest.raises(ServiceError) as e:
        c.job("0" * 32)
    assert e.value.status == 401
    with Client(f"http://127.0.0.1:{free_port()}") as c, pytest.raises(ServiceError) as e:
        c.job("0" * 32)
    assert e.value.code == "unreachable"


def test_client_reports_failed_job(served, sphere):
    with Client(served.url, api_key="sekrit") as c:
        job = c.submit(sphere, max_vertices=64)
        c.cancel(job["id"])
        with pytest.raises(JobFailed) as e:
            c.wait(job["id"], timeout=30)
    assert e.value.job["status"] == "cancelled" and e.value.code == "cancelled"


def run_cli(*args, env=None):
    return subprocess.run([str(Path(sys.executable).with_name("fastmesh")), *args], capture_output=True, text=True,
                          timeout=120, env={**os.environ, **(env or {})})


def test_cli_submit(served, sphere, tmp_path):
    out = tmp_path / "ball.glb"
    r = run_cli("submit", str(sphere), "--url", served.url, "-o", str(out), "--max-vertices", "12", "--seed", "2",
                env={"FASTMESH_API_KEY": "sekrit"})
    assert r.returncode == 0, r.stderr
    assert f"wrote {out}" in r.stderr and "succeeded" in r.stderr
    mesh = trimesh.load(io.BytesIO(out.read_bytes()), file_type="glb", force="mesh")
    assert len(mesh.faces) > 0


def test_cli_submit_errors(served, sphere, tmp_path):
    r = run_cli("submit", str(tmp_path / "missing.xyz"), "--url", served.url)
    assert r.returncode == 2 and "no such file" in r.stderr
    r = run_cli("submit", str(sphere), "--url", served.url, "-o", str(tmp_path / "x.fbx"))
    assert r.returncode == 2 and ".glb, .obj or .ply" in r.stderr
    r = run_cli("submit", str(sphere), "--url", served.url, "--api-key", "nope", "-q")
    assert r.returncode == 1 and "401" in r.stderr and "Traceback" not in r.stderr
    r = run_cli("submit", str(sphere), "--url", served.url, "--api-key", "sekrit", "--temperature", "-1", "-q")
    assert r.returncode == 1 and "temperature" in r.stderr


def test_client_retries_409_with_retry_after_like_429():
    """The service answers 409 conflict + Retry-After while an upload with the same Idempotency-Key is still
    being processed (e.g. its API process died mid-request): the client waits and retries, as for 429.
    A 409 without Retry-After (another file under the same key) is an error at once."""
    answers = [httpx.Response(409, headers={"Retry-After": "0"},
                              json={"error": {"code": "conflict", "message": "still being processed"}}),
               httpx.Response(202, json={"id": "a" * 32, "status": "queued"})]
    keys = []

    def handler(request: httpx.Request) -> httpx.Response:
        keys.append(request.headers["Idempotency-Key"])
        return answers.pop(0)

    c = Client("http://fastmesh.test")
    c.http = httpx.Client(base_url="http://fastmesh.test", transport=httpx.MockTransport(handler))
    f = Path(__file__).with_name("conftest.py")  # any file: the mock does not parse it
    assert c.submit(f)["id"] == "a" * 32
    assert len(keys) == 2 and keys[0] == keys[1]  # the retry carries the same key
    answers.append(httpx.Response(409, json={"error": {"code": "idempotency_conflict", "message": "other file"}}))
    with pytest.raises(ServiceError) as e:
        c.submit(f)
    assert e.value.code == "idempotency_conflict"
