"""What a hostile or careless client did to the service, each now answered cleanly (no worker needed).

Metrics labels from fixed sets only; the API key checked before the body is read, failed keys
rate-limited per address; parameters that could only fail in the worker refused up front; uploads
parsed a bounded number at a time with the costly normal estimation left to the worker; inputs
stored compactly; the Redis of ``make run`` capped without eviction.
"""

from __future__ import annotations

import io
import json
import socket
import threading
import time

import httpx
import numpy as np
import pytest
import redis
from stack import assert_error, make_settings, post, sphere_points, xyz_bytes

import service.http
from fastmesh_jobs.blobs import shape_from_bytes
from fastmesh_jobs.store import Store
from service.processes import RedisServer, ServedApp

KEY = "attack-test-key"


@pytest.fixture(scope="module")
def open_api(redis_url):
    app = ServedApp(make_settings(redis_url, "atk", max_queue_depth=10_000))
    yield app
    app.stop()


@pytest.fixture(scope="module")
def keyed_api(redis_url):
    app = ServedApp(make_settings(redis_url, "atkkey", api_keys=[KEY], auth_fail_limit_per_minute=10,
                                  max_queue_depth=10_000))
    yield app
    app.stop()


def reply_of(s: socket.socket) -> bytes:
    """Everything the server sends until it closes the connection (or 10 s pass)."""
    s.settimeout(10)
    out = b""
    while chunk := s.recv(65536):
        out += chunk
    return out


# ---------------------------------------------------------------------------------------- /metrics


def test_made_up_methods_do_not_grow_the_metrics(open_api):
    """uvicorn accepts any token as a method: each must not become a label value of its own."""
    for i in range(20):
        httpx.request(f"X{i}{'M' * 2000}", f"{open_api.url}/v1/jobs/{'0' * 32}", timeout=10)
    httpx.request("BREW", f"{open_api.url}/no/such/path/{'p' * 500}", timeout=10)
    text = httpx.get(f"{open_api.url}/metrics").text
    assert "MMMM" not in text and "BREW" not in text and "pppp" not in text
    assert 'method="other"' in text
    assert len(text) < 200_000, len(text)


# ---------------------------------------------------------------------------------------- authentication


def test_a_wrong_key_is_refused_before_the_body_is_read(keyed_api):
    """The request declares 30 MB and sends 1 KB of it: the 401 comes at once, not after a body that
    never arrives (before, the server waited for the whole upload)."""
    head = (b"POST /v1/jobs HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer wrong\r\n"
            b"Content-Type: multipart/form-data; boundary=b\r\nContent-Length: 30000000\r\n\r\n")
    with socket.create_connection(("127.0.0.1", keyed_api.port)) as s:
        s.sendall(head + b"--b\r\n" + b"x" * 1024)
        t0 = time.monotonic()
        reply = reply_of(s)
    assert reply.startswith(b"HTTP/1.1 401"), reply[:200]
    assert b'"unauthorized"' in reply and time.monotonic() - t0 < 5


def test_a_stalled_upload_gets_408(redis_url):
    """A client that declares a body and stops sending is answered once ``body_timeout_seconds`` pass."""
    app = ServedApp(make_settings(redis_url, "atkslow", body_timeout_seconds=1))
    try:
        with socket.create_connection(("127.0.0.1", app.port)) as s:
            s.sendall(b"POST /v1/jobs HTTP/1.1\r\nHost: x\r\nContent-Type: multipart/form-data; boundary=b\r\n"
                      b"Content-Length: 5000\r\n\r\n--b\r\n")
            reply = reply_of(s)
        assert reply.startswith(b"HTTP/1.1 408"), reply[:200]
        assert b'"timeout"' in reply and b"body_timeout_seconds" in reply
    finally:
        app.stop()


def test_a_malformed_request_gets_the_json_error_shape(open_api):
    """uvicorn's own answer to a request it cannot parse is plain text; ours is the JSON error of every route."""
    with socket.create_connection(("127.0.0.1", open_api.port)) as s:
        s.sendall(b"NOT AN HTTP REQUEST\r\n\r\n")
        reply = reply_of(s)
    head, _, body = reply.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 400") and b"content-type: application/json" in head.lower(), reply[:300]
    assert json.loads(body)["error"]["code"] == "bad_request"


def test_headers_that_never_finish_get_408(open_api, monkeypatch):
    """A client dripping its request line and headers is answered 408 once ``header_timeout_seconds`` pass after
    their first byte; a prompt request on another connection meanwhile, and keep-alive requests, are not touched."""
    monkeypatch.setattr(service.http, "header_timeout", lambda: 0.5)
    with httpx.Client(base_url=open_api.url, timeout=10) as client, \
            socket.create_connection(("127.0.0.1", open_api.port)) as s:
        s.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\nX-Slow: a")
        t0 = time.monotonic()
        for _ in range(3):  # two requests on one kept-alive connection, spaced past the header timeout
            assert client.get("/healthz").status_code == 200
            time.sleep(0.3)
        reply = reply_of(s)
    assert reply.startswith(b"HTTP/1.1 408"), reply[:200]
    assert json.loads(reply.partition(b"\r\n\r\n")[2])["error"]["code"] == "timeout"
    assert time.monotonic() - t0 < 5


def test_failed_authentication_is_rate_limited_per_address(redis_url):
    app = ServedApp(make_settings(redis_url, "atkrate", api_keys=[KEY], auth_fail_limit_per_minute=10))
    if time.time() % 60 > 45:  # the counter's window is the clock minute: run inside one
        time.sleep(61 - time.time() % 60)
    try:
        codes = [httpx.get(f"{app.url}/v1/jobs/{'0' * 32}", headers={"Authorization": f"Bearer guess{i}"}).status_code
                 for i in range(25)]
        assert codes[:10] == [401] * 10 and set(codes[10:]) == {429}, codes
        # Past the limit even the right key waits: guessing must not learn which key is right.
        r = httpx.get(f"{app.url}/v1/jobs/{'0' * 32}", headers={"Authorization": f"Bearer {KEY}"})
        err = assert_error(r, 429, "rate_limited")
        assert "authentication" in err["message"] and int(r.headers["retry-after"]) > 0
    finally:
        app.stop()


def test_two_authorization_headers_are_refused(keyed_api):
    r = httpx.get(f"{keyed_api.url}/v1/jobs/{'0' * 32}",
                  headers=[("Authorization", f"Bearer {KEY}"), ("Authorization", "Bearer other")])
    assert_error(r, 400, "bad_request")
    ok = httpx.get(f"{keyed_api.url}/v1/jobs/{'0' * 32}", headers={"Authorization": f"Bearer {KEY}"})
    assert_error(ok, 404, "not_found")


# ---------------------------------------------------------------------------------------- validated up front


@pytest.mark.parametrize("temperature", ["1e-39", "1e-30", "0.0000001"])
def test_temperatures_the_sampler_cannot_use_are_422(open_api, temperature):
    err = assert_error(post(open_api.url, "p.xyz", xyz_bytes(sphere_points(50)), temperature=temperature),
                       422, "invalid_parameter")
    assert "temperature" in err["message"] and "0 (greedy)" in err["message"]
    assert post(open_api.url, "p.xyz", xyz_bytes(sphere_points(50)), temperature="0").status_code == 202


def test_max_vertices_is_checked_against_the_last_workers_model_when_none_is_alive(open_api):
    """With no worker up (restarting, scaled to zero), the limit the last one reported still applies:
    4,000 for a 1,000-vertex model used to be accepted and fail later in the worker."""
    store = Store(open_api.settings)
    store.worker_beat("gone-worker", {"max_vertices": 1000})
    store.worker_gone("gone-worker")
    assert store.workers_alive() == []
    err = assert_error(post(open_api.url, "p.xyz", xyz_bytes(sphere_points(50)), max_vertices=4000), 422,
                       "invalid_parameter")
    assert "max_vertices" in err["message"] and "1000" in err["message"]
    assert post(open_api.url, "p.xyz", xyz_bytes(sphere_points(50)), max_vertices=1000).status_code == 202


def test_an_extent_too_small_to_scale_is_422(open_api):
    pts = sphere_points(100, center=(0, 0, 0)) * 1e-310
    buf = io.BytesIO()
    np.save(buf, pts)
    err = assert_error(post(open_api.url, "tiny.npy", buf.getvalue()), 422, "degenerate")
    assert "too small" in err["message"]


# ---------------------------------------------------------------------------------------- parsing


def test_point_cloud_normals_are_left_to_the_worker(open_api):
    """The API stores what the file gave; estimating normals (seconds for a large cloud) is the worker's."""
    r = post(open_api.url, "p.xyz", xyz_bytes(sphere_points(2000)))
    assert r.status_code == 202, r.text
    store = Store(open_api.settings)
    shape = shape_from_bytes(store.get_input(r.json()["id"]))
    assert shape.normals is None
    assert np.array_equal(shape.vertices, np.loadtxt(io.BytesIO(xyz_bytes(sphere_points(2000)))))


def test_inputs_are_stored_compactly_and_exactly(open_api):
    """float32 numbers (what most mesh files hold) take 4 bytes each; other numbers are kept as they are."""
    n = 20_000
    store = Store(open_api.settings)
    for dtype, size in ((np.float32, 4), (np.float64, 8)):
        points = sphere_points(n).astype(dtype)
        blob = store.get_input(post(open_api.url, "p.npy", _npy(points)).json()["id"])
        assert len(blob) < n * 3 * size + 2000, (dtype, len(blob))
        assert np.array_equal(shape_from_bytes(blob).vertices, points.astype(np.float64))


def test_uploads_beyond_the_parsing_slots_get_429(redis_url):
    """One parsing slot and no waiting: of uploads sent together, those finding it taken get 429 busy."""
    app = ServedApp(make_settings(redis_url, "atkparse", max_concurrent_parses=1, parse_wait_seconds=0,
                                  max_queue_depth=10_000))
    try:
        data = xyz_bytes(np.random.default_rng(0).normal(size=(150_000, 3)))  # ~0.5 s to parse
        got: list[httpx.Response] = []
        threads = [threading.Thread(target=lambda: got.append(post(app.url, "big.xyz", data))) for _ in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        codes = sorted(r.status_code for r in got)
        assert 202 in codes and 429 in codes, codes
        busy = next(r for r in got if r.status_code == 429)
        assert_error(busy, 429, "busy")
        assert int(busy.headers["retry-after"]) > 0
    finally:
        app.stop()


def _npy(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, arr)
    return buf.getvalue()


# ---------------------------------------------------------------------------------------- redis


def test_make_runs_redis_is_capped_without_eviction(tmp_path):
    server = RedisServer(directory=str(tmp_path), maxmemory="64mb")
    try:
        r = redis.Redis(port=server.port)
        assert r.config_get("maxmemory-policy")["maxmemory-policy"] == "noeviction"
        assert int(r.config_get("maxmemory")["maxmemory"]) == 64 * 1024 * 1024
    finally:
        server.stop()
