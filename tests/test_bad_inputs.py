"""Bad input over real HTTP: every file below gets a clear 4xx JSON error, or, where it is valid, a job
that ends in a result (or a clear failure code); never a 500, never a dead worker.

Covers zero-byte, truncated and corrupted files of every supported format, wrong extensions, NaN/inf,
one point, identical and collinear points, huge vertex counts, oversize uploads, memory bombs (glTF and
PLY/STL/OFF/npy headers declaring absurd sizes, an npz zip bomb, a flood of text lines: the API's peak
memory is checked), non-UTF-8 and path-traversal filenames, and malformed parameters (hypothesis), plus
the whole OpenAPI schema fuzzed by schemathesis (a third-party client), all bounded.
"""

from __future__ import annotations

import base64
import io
import json
import resource
import struct
import zipfile

import httpx
import numpy as np
import pytest
import schemathesis
import trimesh
from hostile import instanced_glb
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.errors import Unsatisfiable
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    response_schema_conformance,
    status_code_conformance,
)
from stack import assert_error, make_settings, post, sphere_points, wait_final, wp, xyz_bytes

from fastmesh.shapes.shape import SUPPORTED_FORMATS
from fastmesh_jobs.runtime import wait_for
from service.processes import ServedApp

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
LIMITS = dict(max_points=20_000, max_faces=40_000, max_upload_bytes=2_000_000, max_queue_depth=1000)
CLEAR_4XX = (413, 415, 422)


# ---------------------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def served(redis_url, weights, tmp_path_factory):
    """An API and one worker with small limits; the worker must survive the whole module."""
    s = make_settings(redis_url, "bad", weights=weights, **LIMITS)
    app = ServedApp(s)
    worker = wp(s, "bad-w", tmp_path_factory.mktemp("logs") / "w.log").wait_ready()
    yield app, worker
    assert worker.proc.poll() is None, worker.log()[-3000:]
    worker.stop()
    app.stop()


@pytest.fixture(scope="module")
def idle(redis_url):
    """No worker: accepted jobs only queue (parameter fuzzing, schemathesis).  Default upload limits."""
    app = ServedApp(make_settings(redis_url, "badidle", max_queue_depth=100_000))
    yield app
    app.stop()


def outcome(url: str, r: httpx.Response) -> str:
    """'4xx <code>' for a refusal; for an accepted job its final state, 'succeeded' or 'failed <code>'."""
    if r.status_code in CLEAR_4XX:
        return f"{r.status_code} {assert_error(r, r.status_code)['code']}"
    assert r.status_code == 202, (r.status_code, r.text[:300])
    job = wait_final(url, r.json()["id"])
    if job["status"] == "succeeded":
        return "succeeded"
    assert job["status"] == "failed" and job["error"]["code"] not in ("internal", "worker_lost"), job["error"]
    return f"failed {job['error']['code']}"


# ---------------------------------------------------------------------------------------- samples


def gltf_doc(count: int = 42, buf_len: int | None = None, uri: str | None = None, glb: bool = False,
             data: bytes | None = None) -> bytes:
    """A point-mode glTF whose accessor and buffer sizes are what we declare, not what is there."""
    data = data if data is not None else sphere_points(42).astype("<f4").tobytes()
    buf_len = len(data) if buf_len is None else buf_len
    buffer = {"byteLength": buf_len}
    if not glb:
        buffer["uri"] = uri or "data:application/octet-stream;base64," + base64.b64encode(data).decode()
    doc = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
           "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "mode": 0}]}], "buffers": [buffer],
           "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": buf_len}],
           "accessors": [{"bufferView": 0, "componentType": 5126, "count": count, "type": "VEC3",
                          "min": [-1, -1, -1], "max": [1, 1, 1]}]}
    j = json.dumps(doc).encode()
    if not glb:
        return j
    j += b" " * (-len(j) % 4)
    body = data + b"\0" * (-len(data) % 4)
    return (struct.pack("<4sII", b"glTF", 2, 28 + len(j) + len(body)) + struct.pack("<I4s", len(j), b"JSON") + j
            + struct.pack("<I4s", len(body), b"BIN\0") + body)


def npy_bytes(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, arr)
    return buf.getvalue()


def npy_header(shape: tuple, tail: int = 96) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": "<f8", "fortran_order": False, "shape": shape})
    return buf.getvalue() + b"\0" * tail


def valid_samples() -> dict[str, bytes]:
    """One small valid file per supported format (and the ASCII variants of PLY and STL)."""
    from trimesh.exchange.gltf import export_gltf
    from trimesh.exchange.stl import export_stl_ascii

    m = trimesh.creation.icosphere(1)
    pts = sphere_points(200)
    npz = io.BytesIO()
    np.savez(npz, points=pts)
    out = {f"mesh.{f}": m.export(file_type=f) for f in ("obj", "glb", "ply", "stl", "off")}
    out = {k: v.encode() if isinstance(v, str) else v for k, v in out.items()}
    out.update({"mesh.gltf": export_gltf(trimesh.Scene(m), embed_buffers=True)["model.gltf"],
                "ascii.ply": m.export(file_type="ply", encoding="ascii"), "ascii.stl": export_stl_ascii(m).encode(),
                "pts.xyz": xyz_bytes(pts), "pts.txt": xyz_bytes(pts).replace(b" ", b","), "pts.npy": npy_bytes(pts),
                "pts.npz": npz.getvalue()})
    return out


def test_samples_cover_every_supported_format():
    assert {n.rsplit(".", 1)[1] for n in valid_samples()} == set(SUPPORTED_FORMATS)


# ---------------------------------------------------------------------------------------- files


def test_zero_byte_files_of_every_format(served):
    app, _ = served
    for ext in SUPPORTED_FORMATS:
        assert_error(post(app.url, f"empty.{ext}", b""), 422, "empty")


def test_valid_samples_give_results(served):
    app, _ = served
    for name, data in valid_samples().items():
        assert outcome(app.url, post(app.url, name, data, max_vertices=8)) == "succeeded", name


def test_truncated_and_corrupted_files_of_every_format(served):
    """Cut short, bytes flipped, garbage appended, or pure noise: a clear 4xx, or (if the damage left a
    readable shape) a job that ends cleanly.  The worker lives on."""
    app, worker = served
    rng = np.random.default_rng(0)
    seen: dict[str, str] = {}
    for name, data in valid_samples().items():
        variants = {"head7": data[:7], "half": data[: len(data) // 2], "last-byte-cut": data[:-1],
                    "noise": rng.integers(0, 256, len(data), dtype=np.uint8).tobytes(),
                    "tail-garbage": data + rng.integers(0, 256, 64, dtype=np.uint8).tobytes()}
        for k in range(3):  # 2% of the bytes flipped
            b = bytearray(data)
            for i in rng.choice(len(b), max(1, len(b) // 50), replace=False):
                b[i] ^= 1 << int(rng.integers(8))
            variants[f"flip{k}"] = bytes(b)
        for v, blob in variants.items():
            seen[f"{name}:{v}"] = outcome(app.url, post(app.url, name, blob, max_vertices=8))
    assert worker.proc.poll() is None
    refused = [k for k, o in seen.items() if not o.startswith(("succeeded", "failed"))]
    assert len(refused) > len(seen) // 2, seen  # most damage is caught at upload, before any queueing
    assert all(seen[f"{n}:head7"].startswith("422") for n in valid_samples()), seen


@pytest.mark.parametrize("name,data,expect", [
    # wrong or missing extensions
    ("model.exe", b"MZ\x90\x00", "415 unsupported_format"),
    ("noext", b"0 0 0\n1 0 0\n0 1 0\n0 0 1\n", "415 unsupported_format"),
    ("points.xyz.exe", b"0 0 0\n1 0 0\n0 1 0\n0 0 1\n", "415 unsupported_format"),
    ("mesh.fbx", b"Kaydara FBX Binary  \x00", "415 unsupported_format"),
    ("binary-ply-named.obj", trimesh.creation.box().export(file_type="ply"), "422 "),
    ("glb-named.gltf", gltf_doc(glb=True), "422 unreadable"),
    ("text-named.npy", b"0 0 0\n1 1 1\n", "422 unreadable"),
    ("obj-named.stl", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "422 "),
    # non-finite coordinates
    ("nan.xyz", b"0 0 0\n1 0 0\n0 1 0\nnan 0 1\n", "422 non_finite"),
    ("inf.txt", b"0,0,0\n1,0,0\n0,1,0\n0,0,inf\n", "422 non_finite"),
    ("neginf.obj", b"v 0 0 0\nv 1 0 0\nv 0 -inf 0\nf 1 2 3\n", "422 non_finite"),
    ("nan.npy", npy_bytes(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [np.nan, 0, 1.0]])), "422 non_finite"),
    ("overflow.xyz", b"0 0 0\n1 0 0\n0 1 0\n1e400 0 1\n", "422 non_finite"),
    ("nan-normals.xyz", xyz_bytes(np.hstack([sphere_points(50), np.full((50, 3), np.nan)])), "succeeded"),
    # degenerate geometry
    ("one.xyz", b"1 2 3\n", "422 degenerate"),
    ("three.xyz", b"0 0 0\n1 0 0\n0 1 0\n", "422 degenerate"),
    ("same.npy", npy_bytes(np.ones((100, 3))), "422 degenerate"),
    ("line.xyz", b"".join(b"%d %d %d\n" % (i, 2 * i, 3 * i) for i in range(50)), "422 degenerate"),
    ("flat-faces.obj", b"v 0 0 0\nv 1 0 0\nv 2 0 0\nv 3 0 0\nf 1 2 3\nf 2 3 4\n", "422 degenerate"),
    ("face-index.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 1000000000\n", "422 unreadable"),
    ("no-faces.off", b"OFF\n100 0 0\n" + xyz_bytes(sphere_points(100)), "succeeded"),  # a point cloud
    # flat: dense enough that the random networks' vertices, pulled onto it, land on distinct points
    ("planar.xyz", xyz_bytes(np.c_[np.random.default_rng(1).random((1000, 2)), np.zeros(1000)]), "succeeded"),
    ("far.xyz", xyz_bytes(sphere_points(100) * 1e-3 + 1e12), "succeeded"),
    ("tiny.xyz", xyz_bytes(sphere_points(100) * 1e-200, "%.9e"), "succeeded"),
    ("huge-span.xyz", b"-1e308 0 0\n1e308 0 0\n0 1e308 0\n0 0 1e308\n", "422 "),
    ("wrong-width.npy", npy_bytes(np.zeros((10, 4))), "422 unreadable"),
    ("strings.npy", npy_bytes(np.array([["a", "b", "c"]] * 5)), "422 unreadable"),
    ("ragged.xyz", b"0 0 0\n1 0\n0 1 0\n", "422 unreadable"),
    ("words.txt", b"hello world foo\n", "422 unreadable"),
    ("comments-only.xyz", b"# nothing\n# here\n", "422 empty"),
    ("latin1.xyz", b"0 0 0 \xe9\n", "422 unreadable"),
    # too many points or faces for the limits (max_points 20 000, max_faces 40 000)
    ("many.xyz", b"0 0 0\n1 2 3\n" * 10_001, "413 too_large"),
    ("many.npy", npy_bytes(np.random.default_rng(0).random((20_001, 3))), "413 too_large"),
    ("many.obj", b"v 0 0 0\n" * 20_001, "413 too_large"),
    ("many-faces.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\n" + b"f 1 2 3\n" * 40_001, "413 too_large"),
])
def test_bad_files(served, name, data, expect):
    app, _ = served
    assert outcome(app.url, post(app.url, name, data, max_vertices=8)).startswith(expect)


def test_oversize_upload(served):
    app, _ = served
    assert_error(post(app.url, "big.xyz", b"0 0 0\n" * 400_000), 413, "too_large")  # 2.4 MB > 2 MB


def test_memory_bombs_do_not_allocate(idle):
    """Files that declare gigabytes: refused with a 4xx, and the API process (this one) never grows by
    more than a fraction of what they declare."""
    z = io.BytesIO()
    with zipfile.ZipFile(z, "w", zipfile.ZIP_DEFLATED) as zf, zf.open("points.npy", "w", force_zip64=True) as f:
        np.lib.format.write_array_header_1_0(f, {"descr": "<f8", "fortran_order": False, "shape": (4 * 10**7, 3)})
        chunk = b"\0" * (1 << 24)
        for _ in range(4 * 10**7 * 24 // len(chunk)):  # 960 MB of zeros in a ~1 MB upload
            f.write(chunk)
    bombs = {
        "buffer.gltf": gltf_doc(count=2**31, buf_len=2**40),
        "count.gltf": gltf_doc(count=10**9),
        "buffer.glb": gltf_doc(count=2**31, buf_len=2**40, glb=True),
        "count.glb": gltf_doc(count=3 * 10**8, glb=True),
        "bin.ply": b"ply\nformat binary_little_endian 1.0\nelement vertex 1000000000\nproperty double x\n"
                   b"property double y\nproperty double z\nend_header\n" + b"\0" * 120,
        "faces.ply": b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                     b"property float z\nelement face 1000000000\nproperty list uchar int vertex_indices\n"
                     b"end_header\n" + b"\0" * 36 + b"\x03" + b"\0" * 12,
        "ascii.ply": b"ply\nformat ascii 1.0\nelement vertex 1000000000\nproperty float x\nproperty float y\n"
                     b"property float z\nend_header\n0 0 0\n1 0 0\n0 1 0\n",
        "count.stl": b"\0" * 80 + struct.pack("<I", 10**9) + b"\0" * 100,
        "count.off": b"OFF\n1000000000 1000000000 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n",
        "shape.npy": npy_header((10**9, 3)),
        "zipbomb.npz": z.getvalue(),
        "lines.xyz": b"0 0 0\n" * 7_000_000,   # 42 MB of lines: gigabytes as Python lists
        "lines.obj": b"v 0 0 0\n" * 5_000_000,
        # Line ends str.splitlines() honours besides \n: each must count, or end no line at all.
        "cr-lines.xyz": b"0 0 1\r" * 4_000_000,
        "fs-lines.xyz": b"0 0 1\x1c" * 4_000_000,
        "ls-lines.xyz": "0 0 1\u2028".encode() * 3_000_000,
        "instanced.glb": instanced_glb(1200),  # 155 KB: one mesh of 642 vertices shown by 1,200 nodes
    }
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # MiB, peak so far
    got = {n: outcome(idle.url, post(idle.url, n, b)) for n, b in bombs.items()}
    grew = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 - before
    assert all(o[:3] in ("413", "422") for o in got.values()), got
    assert got["zipbomb.npz"] == "413 too_large" and got["lines.xyz"] == "413 too_large", got
    assert got["cr-lines.xyz"] == got["instanced.glb"] == "413 too_large", got
    # The uploads themselves are up to 42 MB and sit in memory a few times over (client, server, parser).
    assert grew < 400, (grew, got)


def test_gltf_external_buffers_are_never_read_from_the_server_disk(served):
    app, _ = served
    for uri in ("../../../../../etc/passwd", "/etc/hostname", "file:///etc/passwd", "http://127.0.0.1:9/x.bin",
                "model.bin"):
        err = assert_error(post(app.url, "ext.gltf", gltf_doc(uri=uri)), 422, "unreadable")
        assert "external file" in err["message"]
    assert outcome(app.url, post(app.url, "embedded.gltf", gltf_doc(), max_vertices=8)) == "succeeded"


# ---------------------------------------------------------------------------------------- filenames


def raw_multipart(filename: bytes, data: bytes) -> tuple[bytes, dict]:
    body = (b'--bnd\r\nContent-Disposition: form-data; name="file"; filename="' + filename + b'"\r\n'
            b"Content-Type: application/octet-stream\r\n\r\n" + data + b"\r\n--bnd--\r\n")
    return body, {"content-type": "multipart/form-data; boundary=bnd"}


@pytest.mark.parametrize("filename,stored", [
    (b"../../../../etc/passwd.xyz", "passwd.xyz"),
    (b"..\\..\\windows\\system32\\p.xyz", "p.xyz"),
    (b"/abs/path/p.xyz", "p.xyz"),
    ("caf\u00e9 \u2603.xyz".encode(), "caf\u00e9 \u2603.xyz"),
    (b"\xff\xfe\xfa.xyz", None),              # not UTF-8: decoded leniently, still a .xyz
    (b"a\x00b.xyz", None),                     # NUL
    (b"x\r\nX-Injected: 1\r\n.xyz", None),      # header injection attempt into the result's Content-Disposition
    (b"....xyz", None),
    (b"a" * 5000 + b".xyz", None),
])
def test_odd_filenames(served, filename, stored):
    app, _ = served
    body, headers = raw_multipart(filename, xyz_bytes(sphere_points(60)))
    r = httpx.post(f"{app.url}/v1/jobs", content=body, headers=headers, timeout=30)
    assert r.status_code in (202, 400, *CLEAR_4XX), r.text  # 400: a header the multipart parser refuses
    if r.status_code != 202:
        assert_error(r, r.status_code)
        return
    job = r.json()
    name = job["input"]["filename"]
    assert "/" not in name and "\\" not in name and "\x00" not in name and "\n" not in name and len(name) <= 200
    if stored:
        assert name == stored
    assert wait_final(app.url, job["id"])["status"] == "succeeded"
    res = httpx.get(f"{app.url}/v1/jobs/{job['id']}/result")
    assert res.status_code == 200
    cd = res.headers["content-disposition"]
    assert cd.isascii() and "\r" not in cd and "\n" not in cd and "x-injected" not in {k.lower() for k in res.headers}


def test_filename_without_extension_or_empty(served):
    app, _ = served
    for fn in (b"", b"   ", b"."):
        body, headers = raw_multipart(fn, b"0 0 0\n")
        r = httpx.post(f"{app.url}/v1/jobs", content=body, headers=headers)
        assert r.status_code in (415, 422), r.text
        assert_error(r, r.status_code)


# ---------------------------------------------------------------------------------------- parameters


@pytest.mark.parametrize("fields", [
    {"temperature": 0}, {"temperature": 5}, {"top_k": 0}, {"top_k": 1}, {"top_k": 1_000_000}, {"top_p": 1e-9},
    {"top_p": 1}, {"max_vertices": 3}, {"max_vertices": 64}, {"seed": 2**32 - 1}, {"enhancer": "false"},
    {"filtering": "false"}, {"formats": "ply,obj,glb"}, {"formats": " GLB , .obj "}, {"candidates": 1},
    {"candidates": 16}, {"topology": "quad", "uv": "true", "origin": "center", "height": "0.0001", "up": "z"},
    {"height": "100000", "origin": "bottom", "uv": "true", "bake": "true"},
])
def test_boundary_parameters_run(served, fields):
    """Accepted extremes must run to a result (or a clear failure), not crash the worker."""
    app, _ = served
    fields.setdefault("max_vertices", 8)
    o = outcome(app.url, post(app.url, "b.xyz", xyz_bytes(sphere_points(100)), **fields))
    assert o == "succeeded" or o.startswith("failed no_"), (fields, o)  # no_vertices / no_faces: a clear answer


FIELD = st.one_of(st.none(), st.text(max_size=12), st.integers(-(2**70), 2**70).map(str),
                  st.floats(allow_nan=True, allow_infinity=True).map(repr), st.sampled_from(["", " ", "1e999", "-0",
                  "true", "false", "0x10", "1_000", "glb,", ",", "glb,glb", "\x00", "\u2603"]))
NAMES = ("seed", "temperature", "top_k", "top_p", "max_vertices", "enhancer", "filtering", "formats", "candidates",
         "topology", "uv", "bake", "origin", "height", "up")


@settings(max_examples=120, deadline=None, suppress_health_check=list(HealthCheck))
@given(values=st.fixed_dictionaries({}, optional={n: FIELD for n in NAMES}))
def test_fuzzed_parameters_never_500(idle, values):
    fields = {k: v for k, v in values.items() if v is not None}
    r = httpx.post(f"{idle.url}/v1/jobs", files={"file": ("p.xyz", xyz_bytes(sphere_points(30)))}, data=fields,
                   timeout=30)
    if r.status_code == 202:
        httpx.delete(f"{idle.url}/v1/jobs/{r.json()['id']}")  # keep the queue short
        return
    err = assert_error(r, 422, "invalid_parameter")
    assert any(n in err["message"] for n in NAMES), err


# ---------------------------------------------------------------------------------------- schemathesis


def operations(url: str):
    return [r.ok() for r in schemathesis.openapi.from_url(f"{url}/openapi.json").get_all_operations()]


@pytest.mark.parametrize("mode", ["positive", "negative"])
def test_openapi_schema_fuzz(idle, mode):
    """Every operation of the OpenAPI schema, with requests schemathesis generates from it (valid ones, then
    ones that break the schema): no 5xx, documented status codes, content types and response bodies."""
    ops = operations(idle.url)
    assert {"POST /v1/jobs", "GET /v1/jobs/{job_id}", "GET /v1/jobs/{job_id}/result"} <= {
        f"{o.method.upper()} {o.path}" for o in ops}
    checks = [status_code_conformance, content_type_conformance, response_schema_conformance]
    for op in ops:
        @settings(max_examples=20, deadline=None, suppress_health_check=list(HealthCheck), database=None)
        @given(case=op.as_strategy(generation_mode=schemathesis.GenerationMode(mode)))
        def check(case):
            if case.path == "/v1/jobs/{job_id}/result" and isinstance(case.query, dict) and "wait" in case.query:
                case.query["wait"] = 0  # a long poll of a queued job would only wait
            response = case.call(base_url=idle.url, timeout=30)
            no_worker = case.path == "/readyz" and response.status_code == 503  # this app has none: documented 503
            assert response.status_code < 500 or no_worker, (case.method, case.path, response.text[:300])
            if mode == "positive":
                case.validate_response(response, checks=checks)
            ctype = response.headers.get("content-type") or [""]  # schemathesis: header -> list of values
            if response.status_code >= 400 and ctype[0].startswith("application/json"):
                assert set(response.json()) == {"error"}, response.text[:300]
            if case.method == "POST" and response.status_code == 202:  # a job, or a batch's jobs
                for job_id in response.json().get("job_ids") or [response.json()["id"]]:
                    httpx.delete(f"{idle.url}/v1/jobs/{job_id}")

        try:
            check()
        except Unsatisfiable:  # nothing to break in an operation without parameters
            assert mode == "negative", op.path


def test_worker_still_serves_after_everything(served):
    app, worker = served
    assert worker.proc.poll() is None
    job = post(app.url, "ok.xyz", xyz_bytes(sphere_points(100)), max_vertices=8).json()
    assert wait_final(app.url, job["id"])["status"] == "succeeded"
    wait_for(lambda: httpx.get(f"{app.url}/readyz").status_code == 200, 10, what="readyz")


def test_io_guards_count_before_parsing():
    """The checks added to fastmesh.shapes.io for the bombs above, at the library level."""
    from fastmesh.shapes.io import load_shape
    from fastmesh.shapes.shape import ShapeError

    # Comment and blank lines do not count as points; one point more than the limit does.
    ok = b"# header\n\n" * 50 + xyz_bytes(sphere_points(100))
    assert len(load_shape(ok, "a.xyz", max_points=100).vertices) == 100
    with pytest.raises(ShapeError) as e:
        load_shape(ok + b"1 1 1\n", "a.xyz", max_points=100)
    assert e.value.code == "too_large"
    with pytest.raises(ShapeError) as e:
        load_shape(npy_header((101, 3)), "a.npy", max_points=100)
    assert e.value.code == "too_large"
    z = io.BytesIO()
    np.savez_compressed(z, points=np.zeros((101, 3)))
    with pytest.raises(ShapeError) as e:
        load_shape(z.getvalue(), "a.npz", max_points=100)
    assert e.value.code == "too_large"
    with pytest.raises(ShapeError) as e:
        load_shape(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2 3\n", "a.obj", max_faces=1)
    assert e.value.code == "too_large"
    with pytest.raises(ShapeError) as e:
        load_shape(gltf_doc(uri="../secret.bin"), "a.gltf")
    assert e.value.code == "unreadable" and "external" in e.value.message
    assert len(load_shape(gltf_doc(), "a.gltf").vertices) == 42


def test_io_textured_obj_and_old_gltf():
    """Found with the assimp corpus: a textured OBJ needed an image library (PIL) only to copy its material;
    glTF 1.0 got a misleading message."""
    from fastmesh.shapes.io import load_shape
    from fastmesh.shapes.shape import ShapeError

    obj = (b"mtllib missing.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nvt 0 0\nvt 1 0\nvt 0 1\nusemtl skin\n"
           b"f 1/1 2/2 3/3\nf 1/1 2/2 4/3\no second\nusemtl other\nf 1/1 3/3 4/2\n")
    s = load_shape(obj, "textured.obj")
    assert s.kind == "mesh" and len(s.faces) == 3
    with pytest.raises(ShapeError) as e:
        load_shape(json.dumps({"asset": {"version": "1.0"}, "buffers": {"b": {"uri": "x.bin"}}}).encode(), "a.gltf")
    assert e.value.code == "unreadable" and "glTF 2.0" in e.value.message


# ---------------------------------------------------------------------------------------- extremes and wording


def ply_double(mesh: trimesh.Trimesh) -> bytes:
    """Binary PLY with float64 vertices (trimesh writes float32)."""
    head = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(mesh.vertices)}\nproperty double x\n"
            f"property double y\nproperty double z\nelement face {len(mesh.faces)}\n"
            "property list uchar int vertex_indices\nend_header\n").encode()
    faces = np.zeros(len(mesh.faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])
    faces["n"], faces["v"] = 3, mesh.faces
    return head + np.asarray(mesh.vertices, "<f8").tobytes() + faces.tobytes()


def huge_samples(scale: float = 1e155, scale32: float = 1e37) -> dict[str, bytes]:
    """Every format with coordinates near the top of its number type: float64 ones at ``scale`` (squared
    distances overflow), float32 ones (STL, glTF) at ``scale32``."""
    from trimesh.exchange.gltf import export_gltf

    m64, m32 = trimesh.creation.icosphere(1), trimesh.creation.icosphere(1)
    m64.vertices *= scale
    m32.vertices *= scale32
    pts = sphere_points(200, center=(0, 0, 0)) * scale
    npz = io.BytesIO()
    np.savez(npz, points=pts)
    out = {"huge.xyz": xyz_bytes(pts, "%.9e"), "huge.txt": xyz_bytes(pts, "%.9e").replace(b" ", b","),
           "huge.npy": npy_bytes(pts), "huge.npz": npz.getvalue(), "huge.ply": ply_double(m64),
           "huge.off": m64.export(file_type="off").encode(),
           "huge.obj": "".join(f"v {x:.9e} {y:.9e} {z:.9e}\n" for x, y, z in m64.vertices).encode()
           + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in m64.faces).encode(),
           "huge.stl": m32.export(file_type="stl"), "huge.glb": m32.export(file_type="glb"),
           "huge.gltf": export_gltf(trimesh.Scene(m32), embed_buffers=True)["model.gltf"]}
    return out


def test_huge_samples_cover_every_supported_format():
    assert {n.rsplit(".", 1)[1] for n in huge_samples()} == set(SUPPORTED_FORMATS)


@pytest.mark.parametrize("name", sorted(huge_samples()))
def test_huge_but_finite_coordinates_give_results(served, name):
    """Points 1e155 apart overflowed the kd-tree's squared distances (a 500): every format now runs."""
    app, _ = served
    data = huge_samples()[name]
    assert outcome(app.url, post(app.url, name, data, max_vertices=8)) == "succeeded", name


def test_a_span_beyond_float64_is_a_clear_422(served):
    app, _ = served
    err = assert_error(post(app.url, "span.xyz", b"-1e308 0 0\n1e308 0 0\n0 1e308 0\n0 0 1e308\n"), 422,
                       "out_of_range")
    assert "span" in err["message"] and "scale the shape down" in err["message"]


def test_text_points_end_lines_only_where_the_line_count_does():
    """A 1.2 MB file of carriage-return lines is refused by the count, before any parsing allocates."""
    import tracemalloc

    from fastmesh.shapes.io import load_shape
    from fastmesh.shapes.shape import ShapeError

    tracemalloc.start()
    try:
        for data, code, words in ((b"0 0 1\r" * 200_000, "too_large", "lines exceed"),
                                  (b"0 0 1\x1c" * 200_000, "unreadable", "characters long"),
                                  ("0 0 1\u2028".encode() * 200_000, "unreadable", "characters long")):
            with pytest.raises(ShapeError) as e:
                load_shape(data, "a.xyz", max_points=1000)
            assert e.value.code == code and words in e.value.message, e.value.message
        peak = tracemalloc.get_traced_memory()[1] / 2**20
    finally:
        tracemalloc.stop()
    assert peak < 25, peak  # MiB: the upload and a few copies of its text, no per-line objects (~50 MiB)
    # Old-Mac line ends are still line ends.
    assert len(load_shape(b"0 0 0\r1 0 0\r0 1 0\r0 0 1\r", "a.xyz").vertices) == 4


def test_gltf_instances_are_counted_before_flattening():
    import tracemalloc

    from fastmesh.shapes.io import load_shape
    from fastmesh.shapes.shape import ShapeError

    three = load_shape(instanced_glb(3), "three.glb")
    assert len(three.vertices) == 3 * 642  # what the count below multiplies: one copy per node
    tracemalloc.start()
    try:
        with pytest.raises(ShapeError) as e:
            load_shape(instanced_glb(1200), "many.glb", max_points=500_000)
        peak = tracemalloc.get_traced_memory()[1] / 2**20
    finally:
        tracemalloc.stop()
    assert e.value.code == "too_large" and "770400 vertices" in e.value.message and "instances" in e.value.message
    assert peak < 20, peak  # MiB; flattening 1,200 copies first took hundreds
    doc = json.loads(gltf_doc())
    doc["nodes"] = [{"mesh": 0, "children": [1]}, {"children": [0]}]
    with pytest.raises(ShapeError) as e:
        load_shape(json.dumps(doc).encode(), "cycle.gltf")
    assert e.value.code == "unreadable" and "cycle" in e.value.message


def test_zero_or_nan_normals_are_estimated_not_taken():
    """All-zero normal columns mean "no normals": taken as given they all pointed one way ((0, 0, 1))."""
    from fastmesh.shapes.io import estimate_normals, load_shape
    from fastmesh.shapes.orientation import outward

    pts = sphere_points(300, center=(0, 0, 0))
    zero = load_shape(npy_bytes(np.hstack([pts, np.zeros_like(pts)])), "z.npy")
    assert np.allclose(zero.normals, outward(pts, estimate_normals(pts)))
    assert (np.einsum("ij,ij->i", zero.normals, pts) > 0.9).mean() > 0.95  # outward on a sphere
    mixed = np.hstack([pts, pts * 2.0])
    mixed[:10, 3:] = 0.0
    mixed[10:20, 3:] = np.nan
    got = load_shape(npy_bytes(mixed), "m.npy").normals
    assert np.allclose(got[20:], pts[20:])  # given ones kept (made unit)
    assert np.allclose(got[:20], estimate_normals(pts)[:20])


def test_truncated_binary_ply_says_what_is_missing():
    from fastmesh.shapes.io import load_shape
    from fastmesh.shapes.shape import ShapeError

    data = trimesh.creation.box().export(file_type="ply")
    # The body is 8 x 12 bytes of vertices and 12 x 13 of triangles: 252 bytes.
    for cut, words in ((data[:-232], ("truncated", "8 vertices, 12 faces", "at least 108 bytes", "only 20 bytes")),
                       (data[:-1], ("does not match its header", "8 vertices, 12 faces", "252 bytes", "251 bytes"))):
        with pytest.raises(ShapeError) as e:
            load_shape(cut, "box.ply")
        assert all(w in e.value.message for w in words), e.value.message
        assert "unexpected length" not in e.value.message


INTERNALS = ("Error", "NoneType", "subscriptable", "unexpected length", "'quad'", "unpack", "reshape", "Traceback")


def test_parser_errors_are_worded_for_people():
    """Damaged files of every format: each refusal names the problem, never a parser's internals."""
    from fastmesh.shapes.io import load_shape
    from fastmesh.shapes.shape import ShapeError

    rng = np.random.default_rng(1)
    messages = {}
    for name, data in valid_samples().items():
        variants = [data[:7], data[: len(data) // 3], data[: len(data) // 2], data[:-1],
                    rng.integers(0, 256, len(data), dtype=np.uint8).tobytes()]
        for _ in range(6):
            b = bytearray(data)
            for i in rng.choice(len(b), max(1, len(b) // 50), replace=False):
                b[i] ^= 1 << int(rng.integers(8))
            variants.append(bytes(b))
        for v in variants:
            try:
                load_shape(v, name, normals=False)
            except ShapeError as e:
                messages[e.message] = name
    assert len(messages) > 20
    bad = {m: n for m, n in messages.items() if any(w in m for w in INTERNALS)}
    assert not bad, bad
