"""``GET /v1/jobs/{id}/preview.png`` and ``.../input.ply`` over real HTTP against real Redis.

No worker here: a job's input is what POST /v1/jobs stored; a "finished" job is made by writing
what a worker writes (start, result npz, finish) through :class:`fastmesh_jobs.store.Store`, so each
case is exact and fast.  The worker path end to end is in ``test_web_browser.py``.

Redis: database ``FASTMESH_TEST_WEB_REDIS_DB`` (default 9) of 127.0.0.1:6379.  Never flushed: every
app gets a key prefix and queue unique to this run, and its keys are deleted when it stops, so test
runs that overlap (CI, several people on one machine) cannot delete each other's jobs.
"""

from __future__ import annotations

import io
import os
import uuid
from contextlib import contextmanager

import httpx
import numpy as np
import pytest
import redis
import trimesh
from test_render import decode_png

from fastmesh_jobs.blobs import mesh_to_bytes
from fastmesh_jobs.settings import Settings
from fastmesh_jobs.store import Store
from service.preview import cache_field, cache_key
from service.processes import ServedApp, local_redis

DB = int(os.environ.get("FASTMESH_TEST_WEB_REDIS_DB", "9"))
BACKGROUND = np.round(np.array([0.965, 0.968, 0.975]) * 255)  # fastmesh.preview.render.RenderConfig.background


def sphere_xyz(n: int = 400) -> bytes:
    rng = np.random.default_rng(0)
    p = rng.normal(size=(n, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    buf = io.StringIO()
    np.savetxt(buf, p + [5.0, 0.0, -2.0], fmt="%.6f")
    return buf.getvalue().encode()


def covered(img: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels that are not background."""
    return np.abs(img[..., :3].astype(float) - BACKGROUND).max(-1) > 6


RUN = uuid.uuid4().hex[:8]  # this test run's mark in every key prefix, queue and worker name


@pytest.fixture(scope="module")
def redis_url():
    url, server = local_redis(DB)
    yield url
    if server:
        server.stop()


def settings_for(redis_url: str, name: str, **kw) -> Settings:
    """Settings of an app whose keys and queue belong to this run alone (``tp-<run>-<name>``)."""
    unique = f"tp-{RUN}-{name}"
    kw = {"rate_limit_per_minute": 0, "submit_rate_limit_per_minute": 0, **kw}
    return Settings(redis_url=redis_url, redis_prefix=unique, queue_name=unique, **kw)


def forget(settings: Settings) -> None:
    """Delete every key of this app: its prefix, its RQ queue's keys and the RQ jobs that came from it."""
    r = redis.Redis.from_url(settings.redis_url)
    q = settings.queue_name
    keys = [*r.scan_iter(f"{settings.redis_prefix}:*"), *r.scan_iter(f"rq:*:{q}"), *r.scan_iter(f"rq:*:{q}:*")]
    keys += [k for k in r.scan_iter("rq:job:*") if r.hget(k, "origin") == q.encode()]
    if keys:
        r.delete(*keys)
    r.srem("rq:queues", f"rq:queue:{q}")  # RQ's registry of queues (a set, not a key per queue)


@contextmanager
def served(settings: Settings):
    """The API on a free port for the block; stopped and its keys deleted afterwards."""
    app = ServedApp(settings)
    try:
        yield app
    finally:
        app.stop()
        forget(settings)


@pytest.fixture(scope="module")
def open_app(redis_url):
    with served(settings_for(redis_url, "open")) as app:
        yield app, Store(app.settings), httpx.Client(base_url=app.url, timeout=30)


def submit(client: httpx.Client, data: bytes = None, name: str = "sphere.xyz", headers=None) -> str:
    r = client.post("/v1/jobs", files={"file": (name, data or sphere_xyz())}, headers=headers or {})
    assert r.status_code == 202, r.text
    return r.json()["id"]


def finish(store: Store, job_id: str, vertices, faces) -> None:
    """Write what a worker writes when a job succeeds."""
    assert store.start(job_id, 1, "test-double-of-a-worker")
    store.put_result(job_id, "npz", mesh_to_bytes(vertices, faces))
    assert store.finish(job_id, 1, "succeeded", result={"vertices": len(vertices), "faces": len(faces),
                                                        "tokens": len(vertices), "formats": []})


def png(r: httpx.Response) -> np.ndarray:
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "image/png"
    return decode_png(r.content)


def test_input_point_cloud_is_previewed_before_the_result_exists(open_app):
    _, _, c = open_app
    job_id = submit(c)
    r = c.get(f"/v1/jobs/{job_id}/preview.png", params={"size": 128})
    img = png(r)
    assert img.shape == (128, 128, 3)
    assert r.headers["x-preview-of"] == "input"
    assert r.headers["cache-control"] == "no-cache"  # the same URL shows the result later
    frac = covered(img).mean()
    assert 0.2 < frac < 0.9, frac  # a framed sphere of splats, not an empty or a flooded image


def test_result_preview_replaces_the_input_and_is_shaded(open_app):
    _, store, c = open_app
    job_id = submit(c)
    before = png(c.get(f"/v1/jobs/{job_id}/preview.png", params={"size": 128}))
    box = trimesh.creation.box(extents=(2.0, 1.0, 1.5))
    finish(store, job_id, box.vertices + 7.0, box.faces)
    r = c.get(f"/v1/jobs/{job_id}/preview.png", params={"size": 128})
    img = png(r)
    assert r.headers["x-preview-of"] == "result"
    assert "max-age" in r.headers["cache-control"]
    assert not np.array_equal(img, before)
    assert covered(img)[img.shape[0] // 2, img.shape[1] // 2]  # the box sits in the middle of the frame
    # Three faces of a box are visible from the 3/4 view, each flat-shaded a different grey.
    shades = {tuple(p) for p in img[covered(img)].reshape(-1, 3)[:, :3] // 8}
    assert len(shades) >= 3


def test_wireframe_draws_dark_edges_and_is_cached_separately(open_app):
    _, store, c = open_app
    job_id = submit(c)
    sphere = trimesh.creation.icosphere(subdivisions=1)
    finish(store, job_id, sphere.vertices, sphere.faces)
    plain = png(c.get(f"/v1/jobs/{job_id}/preview.png", params={"size": 128}))
    wired = png(c.get(f"/v1/jobs/{job_id}/preview.png", params={"size": 128, "wireframe": 1}))
    dark = lambda im: int((im[..., :3].max(-1) < 90).sum())  # noqa: E731
    assert dark(wired) > dark(plain) + 100
    for wire in (False, True):
        assert store.redis.hexists(cache_key(store, job_id), cache_field("result", 128, wire))


def test_preview_is_rendered_once_then_served_from_the_cache(open_app):
    _, store, c = open_app
    job_id = submit(c)
    box = trimesh.creation.box()
    finish(store, job_id, box.vertices, box.faces)
    first = c.get(f"/v1/jobs/{job_id}/preview.png", params={"size": 64})
    key = cache_key(store, job_id)
    assert store.redis.hget(key, cache_field("result", 64, False)) == first.content
    assert 0 < store.redis.ttl(key) <= store.settings.retention_seconds  # expires with the job
    # Without the mesh, only the cache can answer: same bytes.
    store.redis.delete(store.k_result(job_id, "npz"), store.k_input(job_id))
    again = c.get(f"/v1/jobs/{job_id}/preview.png", params={"size": 64})
    assert again.status_code == 200 and again.content == first.content
    # Another size is a different rendering; with nothing left to render it is a clear 404.
    gone = c.get(f"/v1/jobs/{job_id}/preview.png", params={"size": 128})
    assert gone.status_code == 404 and gone.json()["error"]["code"] == "not_found"


def test_deleting_a_job_deletes_its_cached_previews(open_app):
    _, store, c = open_app
    job_id = submit(c)
    box = trimesh.creation.box()
    finish(store, job_id, box.vertices, box.faces)
    assert c.get(f"/v1/jobs/{job_id}/preview.png", params={"size": 64}).status_code == 200
    assert store.redis.exists(cache_key(store, job_id))
    assert c.delete(f"/v1/jobs/{job_id}").status_code == 204
    assert not store.redis.exists(cache_key(store, job_id))


@pytest.mark.parametrize("query", [{"size": 63}, {"size": 1025}, {"size": "big"}, {"size": 2.5}, {"size": 384},
                                   {"wireframe": "maybe"}])
def test_bad_preview_parameters_are_422_json(open_app, query):
    _, _, c = open_app
    job_id = submit(c)
    r = c.get(f"/v1/jobs/{job_id}/preview.png", params=query)
    assert r.status_code == 422
    assert r.json()["error"]["code"] == "invalid_parameter"
    assert next(iter(query)) in r.json()["error"]["message"]


@pytest.mark.parametrize("size", [64, 1024])
def test_size_bounds_are_inclusive(open_app, size):
    _, _, c = open_app
    job_id = submit(c, sphere_xyz(50))
    r = c.get(f"/v1/jobs/{job_id}/preview.png", params={"size": size})
    assert r.status_code == 200
    assert r.content[16:24] == size.to_bytes(4, "big") * 2  # IHDR width, height


def test_unknown_malformed_and_deleted_jobs_are_404(open_app):
    _, _, c = open_app
    for job_id in ("0" * 32, "not-a-job"):
        r = c.get(f"/v1/jobs/{job_id}/preview.png")
        assert r.status_code == 404 and r.json()["error"]["code"] == "not_found"
    job_id = submit(c)
    assert c.delete(f"/v1/jobs/{job_id}").status_code in (200, 204)
    if c.get(f"/v1/jobs/{job_id}").status_code == 200:  # a queued job is cancelled first, then deleted
        assert c.delete(f"/v1/jobs/{job_id}").status_code == 204
    assert c.get(f"/v1/jobs/{job_id}/preview.png").status_code == 404
    assert c.get(f"/v1/jobs/{job_id}/input.ply").status_code == 404


def test_failed_job_previews_its_input(open_app):
    _, store, c = open_app
    job_id = submit(c)
    assert store.start(job_id, 1, "w")
    assert store.finish(job_id, 1, "failed", error={"code": "generation_failed", "message": "x"})
    r = c.get(f"/v1/jobs/{job_id}/preview.png", params={"size": 64})
    assert r.status_code == 200 and r.headers["x-preview-of"] == "input"


def test_result_without_faces_is_drawn_as_points(open_app):
    _, store, c = open_app
    job_id = submit(c)
    finish(store, job_id, np.random.default_rng(1).normal(size=(30, 3)), np.zeros((0, 3), np.int64))
    img = png(c.get(f"/v1/jobs/{job_id}/preview.png", params={"size": 64}))
    assert covered(img).any()


def test_input_ply_of_a_point_cloud(open_app):
    _, _, c = open_app
    job_id = submit(c, sphere_xyz(400))
    r = c.get(f"/v1/jobs/{job_id}/input.ply")
    assert r.status_code == 200 and r.headers["content-type"] == "application/ply"
    cloud = trimesh.load(io.BytesIO(r.content), file_type="ply")
    assert len(cloud.vertices) == 400
    # The input's own frame (results come back in it too), not a normalised one.
    assert np.allclose(cloud.vertices.mean(0), [5.0, 0.0, -2.0], atol=0.2)
    few = trimesh.load(io.BytesIO(c.get(f"/v1/jobs/{job_id}/input.ply", params={"points": 50}).content),
                       file_type="ply")
    assert len(few.vertices) == 50
    assert c.get(f"/v1/jobs/{job_id}/input.ply", params={"points": 0}).status_code == 422


def test_input_ply_of_a_mesh_samples_its_surface(open_app):
    _, _, c = open_app
    box = trimesh.creation.box(extents=(4.0, 2.0, 1.0))
    job_id = submit(c, box.export(file_type="obj").encode(), name="box.obj")
    r = c.get(f"/v1/jobs/{job_id}/input.ply", params={"points": 300})
    pts = np.asarray(trimesh.load(io.BytesIO(r.content), file_type="ply").vertices)
    assert pts.shape == (300, 3)
    # Every sample lies on the box's surface: at least one coordinate at its extent.
    on_face = np.isclose(np.abs(pts) / [2.0, 1.0, 0.5], 1.0, atol=1e-4).any(1)
    assert on_face.all()
    img = png(c.get(f"/v1/jobs/{job_id}/preview.png", params={"size": 64, "wireframe": 1}))
    assert covered(img)[32, 32]


def test_keys_isolate_previews(redis_url):
    with served(settings_for(redis_url, "keys", api_keys=["alpha-key", "beta-key"])) as app:
        alpha = httpx.Client(base_url=app.url, headers={"Authorization": "Bearer alpha-key"})
        beta = httpx.Client(base_url=app.url, headers={"Authorization": "Bearer beta-key"})
        anon = httpx.Client(base_url=app.url)
        job_id = submit(alpha)
        for path in ("preview.png", "input.ply"):
            assert alpha.get(f"/v1/jobs/{job_id}/{path}").status_code == 200
            r = beta.get(f"/v1/jobs/{job_id}/{path}")
            assert r.status_code == 404 and r.json()["error"]["code"] == "not_found"
            r = anon.get(f"/v1/jobs/{job_id}/{path}")
            assert r.status_code == 401 and r.json()["error"]["code"] == "unauthorized"


def test_an_apps_keys_are_all_forgotten(redis_url):
    """The clean-up the other tests rely on to share a database with concurrent runs."""
    s = settings_for(redis_url, "forget")
    with served(s) as app:
        submit(httpx.Client(base_url=app.url))
        r = redis.Redis.from_url(redis_url)
        assert any(r.scan_iter(f"{s.redis_prefix}:*")) and any(r.scan_iter(f"rq:*:{s.queue_name}"))
    assert not any(r.scan_iter(f"*{s.queue_name}*"))
    assert f"rq:queue:{s.queue_name}".encode() not in r.smembers("rq:queues")
    assert not any(r.hget(k, "origin") == s.queue_name.encode() for k in r.scan_iter("rq:job:*"))


def big_result(store: Store, c: httpx.Client) -> str:
    """A succeeded job whose result is dense enough that a 1024 px render takes a noticeable time."""
    job_id = submit(c)
    sphere = trimesh.creation.icosphere(subdivisions=5)  # 20,480 faces
    finish(store, job_id, sphere.vertices, sphere.faces)
    return job_id


def get_all(c: httpx.Client, urls: list[str]) -> list[httpx.Response]:
    """The URLs requested at the same time, one thread each.  The renders wait for two slots in turn: on a
    loaded 2-core machine the last of eight dense ones ended after the client's usual 30 s, so each request
    waits up to 180 s here (the tests time what is refused, not how fast a render is)."""
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(len(urls)) as pool:
        return list(pool.map(lambda url: c.get(url, timeout=180), urls))


def test_concurrent_requests_for_one_preview_render_it_once(open_app):
    """Single flight: 16 requests at once for one (job, size, wireframe) cost one render, all get its bytes."""
    app, store, c = open_app
    job_id = big_result(store, c)
    before = app.app.state.previews.renders
    got = get_all(c, [f"/v1/jobs/{job_id}/preview.png?size=512" for _ in range(16)])
    assert {r.status_code for r in got} == {200}
    assert len({r.content for r in got}) == 1
    assert app.app.state.previews.renders - before == 1
    assert store.redis.hkeys(cache_key(store, job_id)) == [cache_field("result", 512, False).encode()]


def test_the_size_asked_is_the_size_served_or_refused(open_app):
    """Every rendered size comes back as asked; any other is a 422 that names the sizes, never an image of
    another size (a 384 px request once got 512 px)."""
    _, store, c = open_app
    job_id = submit(c, sphere_xyz(50))
    for size in (64, 128, 256, 512, 1024):
        r = c.get(f"/v1/jobs/{job_id}/preview.png", params={"size": size})
        assert r.status_code == 200 and r.content[16:24] == size.to_bytes(4, "big") * 2, size
    for size in (65, 100, 384, 1000):
        err = c.get(f"/v1/jobs/{job_id}/preview.png", params={"size": size}).json()["error"]
        assert err == {"code": "invalid_parameter", "message": f"size: {size} px is not one of the rendered sizes "
                       "64, 128, 256, 512, 1024; ask for one of them and scale the image where you need another"}
    assert store.redis.hlen(cache_key(store, job_id)) == 5
    assert 0 < store.redis.ttl(cache_key(store, job_id)) <= 3600  # previews live an hour, not the job's 24 h


def test_more_pending_renders_than_the_bound_are_refused_at_once(open_app):
    """Distinct renders beyond ``max_pending`` get 503 + Retry-After without waiting; the rest succeed."""
    from service.preview import DEFAULT_PREVIEW

    _, store, c = open_app
    jobs = [big_result(store, c) for _ in range(DEFAULT_PREVIEW.max_pending + 6)]
    got = get_all(c, [f"/v1/jobs/{j}/preview.png?size=1024&wireframe=1" for j in jobs])
    codes = [r.status_code for r in got]
    assert set(codes) <= {200, 503} and codes.count(200) >= DEFAULT_PREVIEW.max_concurrent_renders, codes
    busy = [r for r in got if r.status_code == 503]
    assert busy, codes
    assert all(r.json()["error"]["code"] == "busy" and int(r.headers["retry-after"]) > 0 for r in busy)
    assert all(r.elapsed.total_seconds() < 2 for r in busy)


def test_render_processes_end_with_the_api_process_even_when_it_is_killed():
    """An API stopped by SIGKILL runs no shutdown: its render processes must notice and exit on their own."""
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    code = ("import trimesh\nfrom service.render_pool import RenderPool\n"
            "from fastmesh_jobs.blobs import mesh_to_bytes\n"
            "m = trimesh.creation.box()\npool = RenderPool(2)\n"
            "print(len(pool.render('result', mesh_to_bytes(m.vertices, m.faces), 64, False, 60)), flush=True)\n"
            "import time; time.sleep(120)\n")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert int(proc.stdout.readline()) > 0
        kids = [int(c) for t in Path(f"/proc/{proc.pid}/task").iterdir() for c in (t / "children").read_text().split()]
        assert kids
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()

    def running(pid: int) -> bool:
        status = Path(f"/proc/{pid}/status")
        return status.exists() and "State:\tZ" not in status.read_text()

    deadline = time.monotonic() + 10
    while any(running(k) for k in kids) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not any(running(k) for k in kids), kids
