"""The HTTP API over real HTTP, against real Redis and a real ``fastmesh-worker`` process.

Redis: database ``FASTMESH_TEST_REDIS_DB`` (default 13) of 127.0.0.1:6379, flushed before and after;
a private redis-server when none answers there.  Each app below has its own key prefix and queue.
"""

from __future__ import annotations

import io
import os
import time

import httpx
import numpy as np
import pytest
import redis
import trimesh
from scipy.spatial import cKDTree
from stack import flushed_redis

from fastmesh_jobs.idempotency import PENDING_TTL
from fastmesh_jobs.runtime import wait_for
from fastmesh_jobs.settings import Settings
from fastmesh_jobs.store import Store
from service.processes import ServedApp, WorkerProcess

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")

DB = int(os.environ.get("FASTMESH_TEST_REDIS_DB", "13"))
FAST = dict(heartbeat_interval=0.2, heartbeat_ttl=2.5, reaper_interval=0.2, progress_interval=0.05,
            rate_limit_per_minute=0, submit_rate_limit_per_minute=0)


def sphere_xyz(n: int = 400, seed: int = 0) -> bytes:
    rng = np.random.default_rng(seed)
    p = rng.normal(size=(n, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    buf = io.StringIO()
    np.savetxt(buf, p * 2.0 + [10.0, -3.0, 5.0], fmt="%.6f")  # off-origin, to check the frame comes back
    return buf.getvalue().encode()


@pytest.fixture(scope="module")
def redis_url():
    with flushed_redis(DB) as url:
        yield url


def make_settings(redis_url: str, name: str, **kw) -> Settings:
    return Settings(redis_url=redis_url, redis_prefix=f"t-{name}", queue_name=f"t-{name}", **{**FAST, **kw})


@pytest.fixture(scope="module")
def served(redis_url, weights, tmp_path_factory):
    """An open app (no keys) with one worker."""
    s = make_settings(redis_url, "open", weights=weights, max_points=5000)
    app = ServedApp(s)
    worker = WorkerProcess(s, "open-w1", tmp_path_factory.mktemp("logs") / "w1.log").wait_ready()
    yield app, worker
    worker.stop()
    app.stop()


@pytest.fixture(scope="module")
def idle(redis_url):
    """An app with no worker: jobs stay queued.  Small limits."""
    s = make_settings(redis_url, "idle", max_queue_depth=3, max_upload_bytes=100_000)
    app = ServedApp(s)
    yield app
    app.stop()


@pytest.fixture(scope="module")
def keyed(redis_url):
    s = make_settings(redis_url, "keyed", api_keys=["key-one", "key-two"], cors_origins=["https://example.com"])
    app = ServedApp(s)
    yield app
    app.stop()


def submit(url: str, data: bytes = None, name: str = "sphere.xyz", headers=None, **fields):
    files = {"file": (name, sphere_xyz() if data is None else data)}
    return httpx.post(f"{url}/v1/jobs", files=files, data={k: str(v) for k, v in fields.items()},
                      headers=headers, timeout=30)


def wait_final(url: str, job_id: str, headers=None, timeout: float = 60.0) -> dict:
    def done():
        r = httpx.get(f"{url}/v1/jobs/{job_id}", headers=headers)
        assert r.status_code == 200, r.text
        j = r.json()
        return j if j["status"] in ("succeeded", "failed", "cancelled") else None

    return wait_for(done, timeout, 0.05, what=f"job {job_id} to finish")


def assert_error(r: httpx.Response, status: int, code: str | None = None) -> dict:
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("application/json")
    body = r.json()
    assert set(body) == {"error"} and set(body["error"]) == {"code", "message"}, body
    if code:
        assert body["error"]["code"] == code, body
    return body["error"]


# ---------------------------------------------------------------------------------------- happy path


def test_upload_poll_download_glb(served):
    app, _ = served
    r = submit(app.url, max_vertices=12, seed=3, formats="glb,obj")
    assert r.status_code == 202, r.text
    job = r.json()
    assert r.headers["location"] == f"/v1/jobs/{job['id']}"
    assert set(job) == {"id", "status", "progress", "created_at", "started_at", "finished_at", "params", "input",
                        "result", "timings", "error", "expires_at", "webhook"}
    assert job["input"] == {"filename": "sphere.xyz", "kind": "points", "points": 400, "vertices": None,
                            "faces": None}
    assert job["params"]["seed"] == 3 and job["params"]["max_vertices"] == 12
    assert job["params"]["formats"] == ["glb", "obj"]
    final = wait_final(app.url, job["id"])
    assert final["status"] == "succeeded", final
    assert final["error"] is None and final["progress"] == {"stage": "done", "fraction": 1.0}
    assert set(final["timings"]) == {"queue", "load", "encode", "vertices", "enhancer", "faces", "filtering",
                                     "weighing", "export", "total"}
    assert all(v is not None and v >= 0 for v in final["timings"].values()), final["timings"]
    stages = sum(v for k, v in final["timings"].items() if k not in ("queue", "total"))
    assert final["timings"]["total"] == pytest.approx(stages, abs=0.1)  # the queue apart
    res = final["result"]
    assert res["formats"] == ["glb", "obj"] and res["faces"] > 0 and res["tokens"] > 0

    glb = httpx.get(f"{app.url}/v1/jobs/{job['id']}/result", params={"format": "glb"})
    assert glb.status_code == 200 and glb.headers["content-type"] == "model/gltf-binary"
    assert 'filename="sphere.glb"' in glb.headers["content-disposition"]
    mesh = trimesh.load(io.BytesIO(glb.content), file_type="glb", force="mesh", process=False)
    assert len(mesh.vertices) == res["vertices"] and len(mesh.faces) == res["faces"]
    # The quality block describes this mesh: its topology as trimesh counts it, its distance to the input.
    q = res["quality"]
    uses = np.array([len(g) for g in trimesh.grouping.group_rows(mesh.edges_sorted, require_count=None)])
    parts = trimesh.graph.connected_components(mesh.edges_unique, nodes=np.unique(mesh.faces), min_len=1)
    assert q["boundary_edges"] == int((uses == 1).sum()) and q["non_manifold_edges"] == int((uses > 2).sum())
    assert q["components"] == len(parts) and q["watertight"] == bool(mesh.is_watertight)
    # A point cloud of a sphere with outward normals encloses a volume: closed=auto closes the result.
    assert q["closed_decision"] == "closed" and q["input_pieces"] == 1 and q["faces"] == res["faces"]
    pts = np.loadtxt(io.BytesIO(sphere_xyz()))
    lo, hi = pts.min(0), pts.max(0)
    scale = 100.0 / (hi - lo).max()  # distances in % of the input's longest side
    samples = mesh.sample(5000, seed=1)  # the protocol's count, another sampler and seed
    d_in = cKDTree(samples).query(pts)[0] * scale   # input points -> result surface
    d_out = cKDTree(pts).query(samples)[0] * scale  # result surface -> input points
    assert q["cd"] == pytest.approx((d_in.mean() + d_out.mean()) / 2, rel=0.15)
    assert 0 < q["cd"] <= q["hd"]
    # In the input's frame (a radius-2 sphere centred at (10, -3, 5)), not the unit cube.
    assert np.allclose(mesh.bounds.mean(0), [10, -3, 5], atol=1.5), mesh.bounds
    # ply was not exported with the job: converted on request, same mesh.
    ply = httpx.get(f"{app.url}/v1/jobs/{job['id']}/result", params={"format": "ply"})
    assert ply.status_code == 200
    mply = trimesh.load(io.BytesIO(ply.content), file_type="ply", process=False)
    assert np.allclose(np.sort(mply.vertices, 0), np.sort(mesh.vertices, 0), atol=1e-5)
    # Everything lives in Redis with the retention TTL; DELETE removes the job, its input and results.
    client = redis.Redis.from_url(app.settings.redis_url)
    keys = [f"t-open:{k}" for k in (f"job:{job['id']}", f"input:{job['id']}", f"result:{job['id']}:glb",
                                     f"result:{job['id']}:obj", f"result:{job['id']}:ply",
                                     f"result:{job['id']}:npz")]
    ttls = [client.ttl(k) for k in keys]
    assert all(0 < t <= app.settings.retention_seconds for t in ttls), ttls
    assert httpx.delete(f"{app.url}/v1/jobs/{job['id']}").status_code == 204
    assert client.exists(*keys) == 0
    assert_error(httpx.get(f"{app.url}/v1/jobs/{job['id']}/result"), 404)


def test_long_poll_result(served):
    app, _ = served
    job = submit(app.url, max_vertices=10, formats="obj").json()
    r = httpx.get(f"{app.url}/v1/jobs/{job['id']}/result", params={"format": "obj", "wait": 60}, timeout=70)
    assert r.status_code == 200 and r.content.startswith(b"#") or b"\nv " in r.content


def test_target_faces_comes_back_with_target_and_achieved(served):
    """target_faces through HTTP: the job's quality block says what was asked, what came (the faces of the file
    served), whether that lies within 20 % and how the count was held.  (The tiny networks' triangles are not
    kept a surface, and their doubled faces cannot be split: tests/test_facecount.py checks the count holds.)"""
    app, _ = served
    job = submit(app.url, max_vertices=12, seed=3, target_faces=300, formats="obj").json()
    final = wait_final(app.url, job["id"])
    assert final["status"] == "succeeded", final
    res, q = final["result"], final["result"]["quality"]
    assert final["params"]["target_faces"] == 300 and q["target_faces"] == 300 and q["faces"] == res["faces"]
    assert q["target_met"] is (abs(res["faces"] - 300) <= 60) and q["count_step"] in ("kept", "simplified", "split")
    obj = httpx.get(f"{app.url}/v1/jobs/{job['id']}/result", params={"format": "obj"})
    mesh = trimesh.load(io.BytesIO(obj.content), file_type="obj", force="mesh", process=False)
    assert len(mesh.faces) == res["faces"]


def test_metrics_and_readyz(served):
    app, _ = served
    r = httpx.get(f"{app.url}/readyz")
    assert r.status_code == 200 and r.json()["workers"] == 1
    text = httpx.get(f"{app.url}/metrics").text
    assert 'fastmesh_jobs_total{status="succeeded"}' in text
    assert 'fastmesh_stage_seconds_bucket{le="+Inf",stage="vertices"}' in text
    for metric in ("cd", "hd"):
        assert f'fastmesh_result_distance_percent_bucket{{le="+Inf",metric="{metric}"}}' in text
    assert "fastmesh_queue_depth" in text and "fastmesh_workers_alive 1.0" in text
    assert 'fastmesh_http_requests_total{method="POST",route="/v1/jobs",status="202"}' in text


def test_openapi_documents_the_interface(served):
    app, _ = served
    spec = httpx.get(f"{app.url}/openapi.json").json()
    paths = spec["paths"]
    assert {"/v1/jobs", "/v1/jobs/{job_id}", "/v1/jobs/{job_id}/result", "/healthz", "/readyz",
            "/metrics"} <= set(paths)
    assert set(paths["/v1/jobs/{job_id}"]) == {"get", "delete"}
    job_schema = spec["components"]["schemas"]["Job"]
    assert job_schema["examples"][0]["status"] == "succeeded"
    form = next(iter(paths["/v1/jobs"]["post"]["requestBody"]["content"].values()))["schema"]
    ref = form["$ref"].rsplit("/", 1)[1]
    props = spec["components"]["schemas"][ref]["properties"]
    assert {"file", "seed", "temperature", "top_k", "top_p", "max_vertices", "enhancer", "filtering",
            "closed", "formats"} <= set(props)
    assert "429" in paths["/v1/jobs"]["post"]["responses"]


# ---------------------------------------------------------------------------------------- errors


@pytest.mark.parametrize("name,data,status,code", [
    ("empty.xyz", b"", 422, "empty"),
    ("junk.ply", b"ply\nformat nonsense\n\x00\x01\x02", 422, "unreadable"),
    ("junk.glb", b"glTF\x02\x00\x00\x00\xff\xff\xff\x7f", 422, "unreadable"),
    ("model.exe", b"MZ\x90\x00", 415, "unsupported_format"),
    ("noext", b"1 2 3\n", 415, "unsupported_format"),
    ("nan.xyz", b"0 0 0\n1 0 0\n0 1 0\nnan 0 1\n", 422, "non_finite"),
    ("same.xyz", b"1 1 1\n" * 10, 422, "degenerate"),
    ("line.xyz", b"".join(b"%d 0 0\n" % i for i in range(10)), 422, "degenerate"),
    ("big.xyz", b"".join(b"%d %d %d\n" % (i, i * i % 7, i % 5) for i in range(5001)), 413, "too_large"),
    ("../../etc/passwd.xyz", b"\xff\xfe not utf8", 422, "unreadable"),
])
def test_bad_uploads_are_clear_4xx(served, name, data, status, code):
    app, _ = served
    assert_error(submit(app.url, data, name=name), status, code)


@pytest.mark.parametrize("fields,word", [
    ({"seed": "abc"}, "seed"), ({"seed": -1}, "seed"), ({"temperature": "nan"}, "temperature"),
    ({"temperature": "inf"}, "temperature"), ({"temperature": -1}, "temperature"), ({"top_p": 1.5}, "top_p"),
    ({"top_k": -1}, "top_k"), ({"max_vertices": 0}, "max_vertices"), ({"max_vertices": "x"}, "max_vertices"),
    ({"enhancer": "maybe"}, "enhancer"), ({"formats": "fbx"}, "formats"), ({"formats": "glb,../x"}, "formats"),
    ({"target_faces": 2}, "target_faces"), ({"target_faces": 10 ** 6}, "target_faces"),
    ({"closed": "yes"}, "closed"), ({"closed": ""}, "closed"),
])
def test_bad_parameters_are_422_naming_the_field(served, fields, word):
    app, _ = served
    err = assert_error(submit(app.url, **fields), 422, "invalid_parameter")
    assert word in err["message"]


def test_max_vertices_above_the_workers_model_limit(served):
    app, _ = served  # the tiny test model decodes at most 64 vertices; its worker says so in Redis
    err = assert_error(submit(app.url, max_vertices=65), 422, "invalid_parameter")
    assert "max_vertices" in err["message"] and "64" in err["message"]


def test_missing_file_and_not_multipart(served):
    app, _ = served
    assert "file" in assert_error(httpx.post(f"{app.url}/v1/jobs", data={"seed": "1"}), 422)["message"]
    assert_error(httpx.post(f"{app.url}/v1/jobs", json={"file": "x"}), 422)
    assert_error(httpx.post(f"{app.url}/v1/jobs", content=b"--x\r\nbroken", headers={
        "content-type": "multipart/form-data; boundary=x"}), 422)


def test_unknown_routes_jobs_and_methods(served):
    app, _ = served
    assert_error(httpx.get(f"{app.url}/v1/jobs/{'0' * 32}"), 404, "not_found")
    assert_error(httpx.get(f"{app.url}/v1/jobs/not-an-id"), 404, "not_found")
    assert_error(httpx.get(f"{app.url}/v1/jobs/{'0' * 32}/result"), 404, "not_found")
    assert_error(httpx.delete(f"{app.url}/v1/jobs/{'0' * 32}"), 404, "not_found")
    assert_error(httpx.get(f"{app.url}/nowhere"), 404, "not_found")
    assert_error(httpx.put(f"{app.url}/v1/jobs"), 405, "method_not_allowed")
    assert_error(httpx.get(f"{app.url}/v1/jobs/{'0' * 32}/result", params={"format": "fbx"}), 422)
    assert_error(httpx.get(f"{app.url}/v1/jobs/{'0' * 32}/result", params={"wait": -1}), 422)


def test_oversize_upload_413_declared_and_streamed(idle):
    big = b"0 0 0\n" * 40_000  # 240 kB > 100 kB limit
    assert_error(submit(idle.url, big), 413, "too_large")

    def chunks():  # no Content-Length: counted as it streams
        body = (b"--b\r\nContent-Disposition: form-data; name=\"file\"; filename=\"a.xyz\"\r\n\r\n" + big
                + b"\r\n--b--\r\n")
        for i in range(0, len(body), 8192):
            yield body[i:i + 8192]

    r = httpx.post(f"{idle.url}/v1/jobs", content=chunks(), headers={"content-type": "multipart/form-data; boundary=b"})
    assert_error(r, 413, "too_large")


def test_readyz_without_worker_and_healthz(idle):
    assert httpx.get(f"{idle.url}/healthz").json() == {"status": "ok"}
    assert "no worker" in assert_error(httpx.get(f"{idle.url}/readyz"), 503, "not_ready")["message"]


def test_queued_job_result_409_cancel_delete_and_queue_full(idle):
    ids = []
    for i in range(3):
        r = submit(idle.url, sphere_xyz(seed=i))
        assert r.status_code == 202, r.text
        ids.append(r.json()["id"])
    assert httpx.get(f"{idle.url}/v1/jobs/{ids[2]}").headers["x-queue-position"] == "2"
    r = submit(idle.url)
    assert_error(r, 429, "queue_full")
    assert int(r.headers["retry-after"]) >= 1
    assert_error(httpx.get(f"{idle.url}/v1/jobs/{ids[0]}/result"), 409, "not_ready")
    r = httpx.get(f"{idle.url}/v1/jobs/{ids[0]}/result", params={"wait": 0.3})
    assert_error(r, 409, "not_ready")
    # Cancel the queued jobs: the queue has room again.
    for job_id in ids:
        r = httpx.delete(f"{idle.url}/v1/jobs/{job_id}")
        assert r.status_code == 200 and r.json()["status"] == "cancelled"
        assert r.json()["error"]["code"] == "cancelled" and r.json()["finished_at"]
    assert_error(httpx.get(f"{idle.url}/v1/jobs/{ids[0]}/result"), 409, "job_cancelled")
    assert submit(idle.url).status_code == 202
    # A second DELETE removes the finished job and its input.
    assert httpx.delete(f"{idle.url}/v1/jobs/{ids[0]}").status_code == 204
    assert_error(httpx.get(f"{idle.url}/v1/jobs/{ids[0]}"), 404)
    client = redis.Redis.from_url(idle.settings.redis_url)
    assert not client.exists(f"t-idle:job:{ids[0]}", f"t-idle:input:{ids[0]}")
    assert 0 < client.ttl(f"t-idle:input:{ids[1]}") <= idle.settings.retention_seconds


def test_queue_entry_lost_with_a_worker_is_requeued(idle):
    """A worker killed between taking the job off the RQ queue and starting it: the reaper puts it back."""
    client = redis.Redis.from_url(idle.settings.redis_url)
    job_id = submit(idle.url, sphere_xyz(seed=9)).json()["id"]
    queue_key = f"rq:queue:{idle.settings.queue_name}"
    assert client.lrem(queue_key, 0, f"{job_id}-1") == 1  # what a dequeue does, minus the start
    wait_for(lambda: client.lpos(queue_key, f"{job_id}-2") is not None, 20, what="the reaper to requeue it")
    assert httpx.get(f"{idle.url}/v1/jobs/{job_id}").json()["status"] == "queued"
    assert httpx.delete(f"{idle.url}/v1/jobs/{job_id}").json()["status"] == "cancelled"
    assert client.lpos(queue_key, f"{job_id}-2") is None  # cancelling took it off the queue


def test_rate_limit_429_with_retry_after(redis_url):
    app = ServedApp(make_settings(redis_url, "rate", rate_limit_per_minute=5))
    try:
        # 2 x limit + 1 requests: a 429 even if a minute boundary passes in between.
        codes = [httpx.get(f"{app.url}/v1/jobs/{'0' * 32}") for _ in range(11)]
        limited = [r for r in codes if r.status_code == 429]
        assert limited, [r.status_code for r in codes]
        assert_error(limited[0], 429, "rate_limited")
        assert 1 <= int(limited[0].headers["retry-after"]) <= 60
        assert httpx.get(f"{app.url}/healthz").status_code == 200  # ops endpoints are not limited
    finally:
        app.stop()


def test_redis_down_is_503_not_500():
    from service.processes import free_port

    app = ServedApp(Settings(redis_url=f"redis://127.0.0.1:{free_port()}/0", **FAST))
    try:
        assert_error(httpx.get(f"{app.url}/v1/jobs/{'0' * 32}"), 503, "unavailable")
        assert_error(submit(app.url), 503, "unavailable")
        assert_error(httpx.get(f"{app.url}/readyz"), 503, "not_ready")
        assert httpx.get(f"{app.url}/healthz").status_code == 200
        m = httpx.get(f"{app.url}/metrics")
        assert m.status_code == 200 and "fastmesh_redis_up 0.0" in m.text
    finally:
        app.stop()


# ---------------------------------------------------------------------------------------- keys


def test_api_keys_isolate_jobs(keyed):
    one, two = {"Authorization": "Bearer key-one"}, {"Authorization": "Bearer key-two"}
    r = submit(keyed.url)
    assert_error(r, 401, "unauthorized")
    assert r.headers["www-authenticate"] == "Bearer"
    assert_error(submit(keyed.url, headers={"Authorization": "Bearer nope"}), 401)
    assert_error(submit(keyed.url, headers={"Authorization": "key-one"}), 401)
    job = submit(keyed.url, headers=one).json()
    url = f"{keyed.url}/v1/jobs/{job['id']}"
    assert httpx.get(url, headers=one).status_code == 200
    assert_error(httpx.get(url), 401)
    assert_error(httpx.get(url, headers=two), 404, "not_found")
    assert_error(httpx.get(f"{url}/result", headers=two), 404, "not_found")
    assert_error(httpx.delete(url, headers=two), 404, "not_found")
    assert httpx.get(url, headers=one).json()["status"] == "queued"  # key two's DELETE did nothing
    assert httpx.get(f"{keyed.url}/healthz").status_code == 200
    assert_error(httpx.get(f"{keyed.url}/metrics"), 401)  # metrics read Redis: behind the key like /v1
    assert httpx.get(f"{keyed.url}/metrics", headers=one).status_code == 200


def test_idempotency_key_scoped_per_api_key(keyed):
    one = {"Authorization": "Bearer key-one", "Idempotency-Key": "upload-42"}
    two = {"Authorization": "Bearer key-two", "Idempotency-Key": "upload-42"}
    a = submit(keyed.url, headers=one, seed=5)
    b = submit(keyed.url, headers=one, seed=5)
    assert a.status_code == 202 and b.status_code == 200
    assert a.json()["id"] == b.json()["id"] and b.headers["location"] == a.headers["location"]
    assert_error(submit(keyed.url, headers=one, seed=6), 409, "idempotency_conflict")
    c = submit(keyed.url, headers=two, seed=5)
    assert c.status_code == 202 and c.json()["id"] != a.json()["id"]
    # Deleting the job frees its key.
    auth = {"Authorization": "Bearer key-one"}
    httpx.delete(f"{keyed.url}/v1/jobs/{a.json()['id']}", headers=auth)
    httpx.delete(f"{keyed.url}/v1/jobs/{a.json()['id']}", headers=auth)
    d = submit(keyed.url, headers=one, seed=6)
    assert d.status_code == 202 and d.json()["id"] != a.json()["id"]


def test_idempotency_key_of_a_request_whose_api_died(keyed):
    """An API process killed mid-request leaves its Idempotency-Key claimed ("pending"): a retry gets the
    job if it was created, and a new one (not a 409 for ever) once the claim of a job never created expires."""
    store = Store(keyed.settings)
    auth = {"Authorization": "Bearer key-one"}
    first = submit(keyed.url, headers={**auth, "Idempotency-Key": "died-1"}, seed=8)
    assert first.status_code == 202
    job_id = first.json()["id"]
    who = store.get(job_id)["owner"]  # the hash of key-one
    claim = store.idempotency_get(who, "died-1")
    assert claim.startswith(f"{job_id} ") and not claim.endswith(" pending")
    # Killed after creating the job, before naming it final.
    store.redis.set(store._k_idem(who, "died-1"), f"{claim} pending", ex=PENDING_TTL)
    again = submit(keyed.url, headers={**auth, "Idempotency-Key": "died-1"}, seed=8)
    assert again.status_code == 200 and again.json()["id"] == job_id
    # Killed before creating the job: the retry waits for the claim to expire, then creates the job.
    fp = claim.split(" ")[1]
    store.redis.set(store._k_idem(who, "died-2"), f"{Store.new_id()} {fp} pending", px=1500)
    t0 = time.monotonic()
    late = submit(keyed.url, headers={**auth, "Idempotency-Key": "died-2"}, seed=8)
    assert late.status_code == 202 and late.json()["id"] != job_id, late.text
    assert 1.0 < time.monotonic() - t0 < 5.0
    assert store.idempotency_get(who, "died-2") == f"{late.json()['id']} {fp}"


def test_concurrent_retries_with_one_idempotency_key_make_one_job(keyed):
    from concurrent.futures import ThreadPoolExecutor

    headers = {"Authorization": "Bearer key-two", "Idempotency-Key": "burst-7"}
    with ThreadPoolExecutor(6) as pool:
        answers = list(pool.map(lambda _: submit(keyed.url, headers=headers, seed=7), range(6)))
    assert sorted(r.status_code for r in answers) == [200] * 5 + [202], [r.text for r in answers]
    assert len({r.json()["id"] for r in answers}) == 1


def test_cors(keyed):
    pre = httpx.options(f"{keyed.url}/v1/jobs", headers={
        "Origin": "https://example.com", "Access-Control-Request-Method": "POST",
        "Access-Control-Request-Headers": "authorization,idempotency-key"})
    assert pre.status_code == 200
    assert pre.headers["access-control-allow-origin"] == "https://example.com"
    r = httpx.get(f"{keyed.url}/v1/jobs/{'0' * 32}", headers={"Origin": "https://example.com"})
    assert r.status_code == 401 and r.headers["access-control-allow-origin"] == "https://example.com"
    assert "retry-after" in r.headers.get("access-control-expose-headers", "").lower()
    other = httpx.get(f"{keyed.url}/healthz", headers={"Origin": "https://evil.example"})
    assert "access-control-allow-origin" not in other.headers
    refused = httpx.options(f"{keyed.url}/v1/jobs", headers={"Origin": "https://evil.example",
                                                            "Access-Control-Request-Method": "PUT"})
    err = assert_error(refused, 400, "cors_refused")  # the JSON error shape, not Starlette's plain text
    assert "origin" in err["message"] and "method" in err["message"]
