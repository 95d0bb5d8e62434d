"""Limits that cannot be turned against other users, strict form values, and what a request may hold open."""

from __future__ import annotations

import re
import socket
import struct
import subprocess
import sys
import time
import zlib
from pathlib import Path

import httpx
import numpy as np
import pytest
from stack import assert_error, make_settings, post, sphere_points, xyz_bytes

import service.render_pool
from fastmesh.shapes.io import load_shape
from fastmesh.shapes.shape import ShapeError
from fastmesh.shapes.texture import MAX_TEXTURE_SIDE
from fastmesh_jobs.blobs import mesh_to_bytes
from fastmesh_jobs.settings import Settings, settings_table
from fastmesh_jobs.store import Store
from service.processes import ServedApp

KEY, KEY2 = "limits-test-key", "limits-test-key-2"
README = Path(__file__).resolve().parents[1] / "README.md"


@pytest.fixture(scope="module")
def open_api(redis_url):
    app = ServedApp(make_settings(redis_url, "lim", max_queue_depth=10_000))
    yield app
    app.stop()


def within_one_minute_window() -> None:
    """The failed-key counter's window is the clock minute: run inside one."""
    if time.time() % 60 > 40:
        time.sleep(61 - time.time() % 60)


def bearer(key: str, **extra: str) -> dict:
    return {"Authorization": f"Bearer {key}", **extra}


# ---------------------------------------------------------------------------------------- failed keys, proxies


def test_failed_keys_do_not_lock_out_a_key_already_in_use_from_the_address(redis_url):
    """Someone guessing from a shared address (a NAT, a proxy, docker's gateway) must not lock out the users
    already working from there; a key first seen during the lockout waits like any guess."""
    app = ServedApp(make_settings(redis_url, "limlock", api_keys=[KEY, KEY2], auth_fail_limit_per_minute=10))
    within_one_minute_window()
    try:
        url = f"{app.url}/v1/jobs/{'0' * 32}"
        assert_error(httpx.get(url, headers=bearer(KEY)), 404)
        codes = [httpx.get(url, headers=bearer(f"guess{i}")).status_code for i in range(20)]
        assert codes[:10] == [401] * 10 and set(codes[10:]) == {429}, codes
        assert_error(httpx.get(url, headers=bearer(KEY)), 404)  # still served
        assert_error(httpx.get(url, headers=bearer(KEY2)), 429, "rate_limited")  # never seen here before
    finally:
        app.stop()


def test_x_forwarded_for_is_ignored_unless_from_a_trusted_proxy(redis_url):
    within_one_minute_window()
    for trusted, expect_429 in (([], True), (["127.0.0.1"], False)):
        app = ServedApp(make_settings(redis_url, f"limxff{len(trusted)}", api_keys=[KEY], auth_fail_limit_per_minute=5,
                                      trusted_proxies=trusted))
        try:
            codes = [httpx.get(f"{app.url}/v1/jobs/{'0' * 32}",
                               headers=bearer(f"guess{i}", **{"X-Forwarded-For": f"198.51.100.{i}"})).status_code
                     for i in range(12)]
            assert (429 in codes) == expect_429, (trusted, codes)
        finally:
            app.stop()


def test_metrics_need_a_key_and_count_against_the_rate_limit(redis_url):
    app = ServedApp(make_settings(redis_url, "limmetrics", api_keys=[KEY], rate_limit_per_minute=5))
    within_one_minute_window()
    try:
        assert_error(httpx.get(f"{app.url}/metrics"), 401, "unauthorized")
        codes = [httpx.get(f"{app.url}/metrics", headers=bearer(KEY)).status_code for _ in range(8)]
        assert codes[:5] == [200] * 5 and set(codes[5:]) == {429}, codes
    finally:
        app.stop()


# ---------------------------------------------------------------------------------------- form values


@pytest.mark.parametrize("field,value", [("target_faces", "1_000"), ("target_faces", "+4"), ("target_faces", " 5 "),
                                         ("target_faces", "4.0"), ("candidates", "2.0"), ("seed", "1.0"),
                                         ("enhancer", "yes"), ("enhancer", "on"), ("enhancer", ""),
                                         ("top_p", "1e-320")])
def test_lax_spellings_are_422(open_api, field, value):
    err = assert_error(post(open_api.url, "p.xyz", xyz_bytes(sphere_points(50)), **{field: value}), 422,
                       "invalid_parameter")
    assert err["message"].startswith(field)


def test_plain_spellings_are_accepted(open_api):
    r = post(open_api.url, "p.xyz", xyz_bytes(sphere_points(50)), target_faces=400, candidates=1, seed=3,
             enhancer="false", filtering="True", top_p="0.5", temperature="1e-3")
    assert r.status_code == 202, r.text


def test_the_idempotency_fingerprint_includes_the_filename(open_api):
    data, key = xyz_bytes(sphere_points(60)), {"Idempotency-Key": f"lim-{time.time()}"}
    assert post(open_api.url, "a.xyz", data, headers=key).status_code == 202
    assert_error(post(open_api.url, "b.xyz", data, headers=key), 409, "idempotency_conflict")


def test_a_utf8_filename_is_kept_and_named_in_the_download(open_api):
    """Browsers send the name as raw UTF-8 bytes in the multipart header; the download names the result after
    it in ``filename*`` (the ASCII ``filename`` has to replace what is not ASCII)."""
    name = "résumé 😀.xyz"
    body = (b"--b\r\nContent-Disposition: form-data; name=\"file\"; filename=\"" + name.encode() + b"\"\r\n"
            b"Content-Type: application/octet-stream\r\n\r\n" + xyz_bytes(sphere_points(50)) + b"\r\n--b--\r\n")
    r = httpx.post(f"{open_api.url}/v1/jobs", content=body, headers={"Content-Type": "multipart/form-data; boundary=b"})
    assert r.status_code == 202, r.text
    assert r.json()["input"]["filename"] == name
    job_id, store = r.json()["id"], Store(open_api.settings)
    assert store.start(job_id, 1, "test-double-of-a-worker")
    store.put_result(job_id, "npz", mesh_to_bytes(np.eye(3), np.array([[0, 1, 2]])))
    assert store.finish(job_id, 1, "succeeded", result={"vertices": 3, "faces": 1, "tokens": 3, "formats": []})
    got = httpx.get(f"{open_api.url}/v1/jobs/{job_id}/result?format=obj", timeout=30)
    assert got.status_code == 200
    assert "filename*=UTF-8''r%C3%A9sum%C3%A9%20%F0%9F%98%80.obj" in got.headers["content-disposition"]


# ---------------------------------------------------------------------------------------- textures for bake


def textured_glb(side: int, mode: str = "RGB") -> bytes:
    """A cube with a base-colour texture of ``side`` x ``side`` pixels of one colour (a small PNG)."""
    import trimesh
    from PIL import Image
    from trimesh.visual import TextureVisuals
    from trimesh.visual.material import PBRMaterial

    box = trimesh.creation.box()
    uv = np.random.default_rng(0).uniform(0, 1, (len(box.vertices), 2))
    image = Image.new(mode, (side, side), 200)
    return trimesh.Trimesh(box.vertices, box.faces, visual=TextureVisuals(uv=uv, material=PBRMaterial(
        baseColorTexture=image)), process=False).export(file_type="glb")


def test_a_texture_over_the_limit_is_a_413_naming_its_size_and_the_limit(open_api):
    side = MAX_TEXTURE_SIDE + 8
    data = textured_glb(side, "L")
    err = assert_error(post(open_api.url, "big.glb", data, uv="true", bake="true"), 413, "too_large")
    assert f"texture is {side} x {side} pixels" in err["message"], err
    assert f"({MAX_TEXTURE_SIDE} x {MAX_TEXTURE_SIDE})" in err["message"] and "bake" in err["message"], err
    assert post(open_api.url, "big.glb", data).status_code == 202  # without bake the texture is not read


def with_image_size(glb: bytes, side: int) -> bytes:
    """``glb`` with its PNG's header saying ``side`` x ``side`` pixels (its pixels left as they are)."""
    start = glb.index(b"\x89PNG\r\n\x1a\n") + 8  # the IHDR chunk: length, type, width, height, ..., CRC
    ihdr = bytearray(glb[start + 4:start + 21])
    ihdr[4:12] = struct.pack(">II", side, side)
    return glb[:start + 4] + bytes(ihdr) + struct.pack(">I", zlib.crc32(ihdr)) + glb[start + 25:]


def test_a_texture_too_large_for_the_image_reader_is_named_too():
    """PIL refuses to open an image of more than ~179 M pixels, which the glTF reader took silently for no texture."""
    data = with_image_size(textured_glb(4), 20_000)
    with pytest.raises(ShapeError) as e:
        load_shape(data, filename="huge.glb", texture=True)
    assert e.value.code == "too_large" and "20000 x 20000 pixels" in e.value.message
    assert len(load_shape(data, filename="huge.glb").faces) == 12  # without bake the texture is not read


PEAK_OF_LOAD = """
import sys
from fastmesh.shapes.io import load_shape
def peak():  # this process's (not its parent's) largest resident size, in MiB
    return int(next(line for line in open("/proc/self/status") if line.startswith("VmHWM")).split()[1]) // 1024
data = sys.stdin.buffer.read()
before = peak()
shape = load_shape(data, filename="t.glb", texture=True)
assert shape.texture is not None and max(shape.texture.images[0].shape[:2]) == 2048
print(peak() - before)
"""


def test_an_8000_pixel_texture_is_read_for_bake_in_bounded_memory():
    """Decoded once at full size (192 MB as RGB) and scaled down in place: copies of the full image (the mesh's
    visuals copied, an RGBA conversion) would take a parse past 1 GB."""
    data = textured_glb(8000)
    run = subprocess.run([sys.executable, "-c", PEAK_OF_LOAD], input=data, capture_output=True, timeout=300,
                         env={"OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"})
    assert run.returncode == 0, run.stderr.decode()[-2000:]
    assert int(run.stdout) < 500, f"loading the texture raised the peak by {int(run.stdout)} MiB"


# ---------------------------------------------------------------------------------------- held open, left behind


def test_a_trickling_upload_meets_its_deadline(redis_url):
    app = ServedApp(make_settings(redis_url, "limtrickle", body_timeout_seconds=5, upload_deadline_seconds=1.5))
    try:
        with socket.create_connection(("127.0.0.1", app.port)) as s:
            s.sendall(b"POST /v1/jobs HTTP/1.1\r\nHost: x\r\nContent-Type: multipart/form-data; boundary=b\r\n"
                      b"Content-Length: 5000\r\n\r\n--b\r\nContent-Disposition: form-data; name=\"file\"; "
                      b"filename=\"a.xyz\"\r\n\r\n")
            t0, reply = time.monotonic(), b""
            s.settimeout(0.3)
            while time.monotonic() - t0 < 10 and not reply:
                try:
                    s.sendall(b"0123456789")
                    reply = s.recv(65536)
                except TimeoutError:
                    continue
                except OSError:
                    break
            s.settimeout(5)
            while reply and b"}" not in reply.partition(b"\r\n\r\n")[2]:  # the body can come in a later segment
                more = s.recv(65536)
                if not more:
                    break
                reply += more
        assert reply.startswith(b"HTTP/1.1 408"), reply[:200]
        assert b"upload_deadline_seconds" in reply and time.monotonic() - t0 < 5
    finally:
        app.stop()


def test_a_preview_finished_after_its_job_was_deleted_is_not_cached(open_api, monkeypatch):
    r = post(open_api.url, "p.xyz", xyz_bytes(sphere_points(400)))
    job_id = r.json()["id"]
    assert httpx.delete(f"{open_api.url}/v1/jobs/{job_id}").status_code == 200  # cancelled: now deletable
    store = Store(open_api.settings)
    render = service.render_pool.RenderPool.render

    def render_then_delete(self, *args, **kw):
        png = render(self, *args, **kw)
        assert httpx.delete(f"{open_api.url}/v1/jobs/{job_id}").status_code == 204
        return png

    monkeypatch.setattr(service.render_pool.RenderPool, "render", render_then_delete)
    httpx.get(f"{open_api.url}/v1/jobs/{job_id}/preview.png?size=64", timeout=60)
    assert not store.redis.exists(store.k_preview(job_id))


# ---------------------------------------------------------------------------------------- README


def test_readme_lists_every_setting():
    """README's settings table is ``settings_table()``: regenerate it with
    ``python -c 'from fastmesh_jobs.settings import settings_table; print(settings_table())'``."""
    readme = README.read_text()
    table = settings_table()
    assert table in readme, "README's settings table differs from fastmesh_jobs.settings.settings_table()"
    for name in Settings.model_fields:
        assert re.search(rf"`FASTMESH_{name.upper()}`", readme), name


def test_the_table_has_a_row_per_setting():
    rows = settings_table().splitlines()[2:]
    assert len(rows) == len(Settings.model_fields)
    assert all(r.count("|") == 4 for r in rows), rows
