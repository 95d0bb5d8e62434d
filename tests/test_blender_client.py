"""The Blender add-on (clients/blender): its HTTP and file logic without Blender, against a stub service over
real HTTP (tests/blender_stub.py) and the real stack with a worker; the zip `make blender-addon` builds; and,
where Debian's ``blender`` is installed (scripts/install-blender.sh), the add-on itself in Blender's
background mode."""

from __future__ import annotations

import ast
import importlib.util
import io
import json
import math
import os
import shutil
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
import redis
import trimesh
from blender_stub import StubServer, error_body
from test_service_api import make_settings, sphere_xyz

from fastmesh.params import TARGET_FACES
from service.processes import ServedApp, WorkerProcess, free_port, local_redis

ROOT = Path(__file__).resolve().parent.parent
ADDON = ROOT / "clients" / "blender"
spec = importlib.util.spec_from_file_location("fastmesh_blender_client", ADDON / "client.py")
client = importlib.util.module_from_spec(spec)
spec.loader.exec_module(client)
DB = int(os.environ.get("FASTMESH_TEST_REDIS_DB", "13"))
CUBE = [(x, y, z) for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)]
CUBE_FACES = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]


@pytest.fixture
def stub():
    s = StubServer()
    yield s
    s.close()


def run_task(c, params, data=None, name="box.obj", **kw):
    task = client.Task(c, name, data if data is not None else client.obj_bytes(CUBE, CUBE_FACES), params,
                       poll=0.01, **kw)
    seen = []
    task.start()
    deadline = time.monotonic() + 20
    while not task.finished() and time.monotonic() < deadline:
        seen.append(task.snapshot())
        time.sleep(0.005)
    task.join(5)
    return task.snapshot(), seen


# ------------------------------------------------------------------------------------- form and files
def test_form_fields_send_only_what_is_set():
    got = client.form_fields({"target_faces": 500, "topology": None, "origin": "bottom", "height": 1.8,
                              "up": None, "closed": "false", "seed": 0, "enhancer": False})
    assert got == {"target_faces": "500", "origin": "bottom", "height": "1.8", "closed": "false", "seed": "0",
                   "enhancer": "false"}
    with pytest.raises(ValueError, match="topology"):
        client.form_fields({"topology": "quads"})
    with pytest.raises(ValueError, match="height"):
        client.form_fields({"height": math.nan})


@pytest.mark.parametrize("url", ["", "localhost:8000", "ftp://h/x", "http://", "http://h:99999", "http://[::1"])
def test_bad_url_is_named(url):
    with pytest.raises(client.ServiceError) as e:
        client.Client(url)
    assert e.value.code == "bad_url" and e.value.status == 0


def test_upload_is_gltf_frame_obj_or_points():
    name, data = client.upload_of("My Cube/1", CUBE, CUBE_FACES)
    assert name == "My_Cube_1.obj"
    mesh = trimesh.load(io.BytesIO(data), file_type="obj", process=False)
    assert len(mesh.vertices) == 8 and len(mesh.faces) == 12  # 6 quads, triangulated by the reader
    tall = [(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 5.0)]  # 5 up Blender's Z -> 5 up glTF's Y
    _, data = client.upload_of("t", tall, [(0, 1, 2)])
    assert np.allclose(trimesh.load(io.BytesIO(data), file_type="obj", process=False).extents, [1, 5, 0])
    name, data = client.upload_of("pts", [(1.5, 2.0, 3.25)], [])
    assert name == "pts.xyz" and np.allclose(np.loadtxt(io.BytesIO(data)), [1.5, 3.25, -2.0])
    with pytest.raises(ValueError, match="no vertices"):
        client.upload_of("empty", [], [])


def test_placement_beside_the_original():
    lo, hi = client.bounds([(1, -1, 0), (3, 2, 4)])
    assert client.placement(lo, hi, None) == (2, 0, 0)
    assert client.placement(lo, hi, "input") == (2, 0, 0)
    assert client.placement(lo, hi, "center") == (4, 0.5, 2)
    assert client.placement(lo, hi, "bottom") == (4, 0.5, 0)
    assert client.import_format({"topology": "quad"}) == "obj" and client.import_format({}) == "glb"
    assert client.up_correction("z", "obj") == -math.pi / 2  # the service's Z-up OBJ, read as Y-up
    assert client.up_correction("z", "glb") == client.up_correction("y", "obj") == 0
    assert client.up_correction(None, "obj") == 0


# ------------------------------------------------------------------------------------- against a stub
def test_task_uploads_polls_downloads(stub):
    stub.stub.key = "sekrit"
    c = client.Client(stub.url + "/", api_key="sekrit")
    snap, seen = run_task(c, {"target_faces": 300, "topology": None, "origin": "center", "seed": None})
    assert snap["state"] == "done", snap
    assert snap["message"] == "done: 8 vertices, 12 faces"
    sub = stub.stub.submissions[0]
    assert sub["fields"] == {"target_faces": "300", "origin": "center", "formats": "glb"}
    assert sub["filename"] == "box.obj" and sub["data"] == client.obj_bytes(CUBE, CUBE_FACES)
    assert sub["headers"]["Idempotency-Key"]
    result = trimesh.load(io.BytesIO(snap["result"]), file_type="glb", force="mesh")
    assert np.allclose(result.bounds, [[-1, -1, -1], [1, 1, 1]])
    states = [(s["state"], s["stage"]) for s in seen]
    assert ("running", "vertices") in states and ("running", "faces") in states
    assert {"queued", "running: vertices", "running: faces"} <= {s["message"] for s in seen}
    fractions = [s["fraction"] for s in seen]
    assert fractions == sorted(fractions) and stub.stub.downloads == ["glb"]


def test_quads_download_obj(stub):
    snap, _ = run_task(client.Client(stub.url), {"topology": "quad"}, fmt="obj")
    assert snap["state"] == "done" and stub.stub.downloads == ["obj"]
    assert stub.stub.submissions[0]["fields"] == {"topology": "quad", "formats": "obj"}
    assert snap["result"].count(b"\nf ") == 6


def test_service_error_json_is_shown(stub):
    stub.stub.reject = (422, error_body("invalid_parameter", "topology: must be triangle or quad"), {})
    snap, _ = run_task(client.Client(stub.url), {"topology": "quad"})
    assert snap["state"] == "failed" and snap["error"] == "invalid_parameter"
    assert "topology: must be triangle or quad (invalid_parameter, HTTP 422)" in snap["message"]
    with pytest.raises(client.ServiceError) as e:
        client.Client(stub.url).submit("a.obj", b"v 0 0 0\n", {})
    assert (e.value.status, e.value.code) == (422, "invalid_parameter")


def test_unauthorised_and_not_json(stub):
    stub.stub.key = "sekrit"
    with pytest.raises(client.ServiceError) as e:
        client.Client(stub.url, api_key="wrong").job("x")
    assert (e.value.status, e.value.code) == (401, "unauthorized")
    stub.stub.key = None
    stub.stub.reject = (502, b"<html>Bad Gateway</html>", {})
    with pytest.raises(client.ServiceError) as e:
        client.Client(stub.url).submit("a.obj", b"v 0 0 0\n", {})
    assert e.value.code == "http_error" and "Bad Gateway" in e.value.message


def test_busy_service_is_retried(stub):
    stub.stub.busy = 2
    snap, _ = run_task(client.Client(stub.url), {})
    assert snap["state"] == "done" and len(stub.stub.submissions) == 1


def test_failed_job_reports_the_services_reason(stub):
    stub.stub.outcome = "failed"
    snap, _ = run_task(client.Client(stub.url), {})
    assert snap["state"] == "failed" and snap["message"] == "job failed: the model made no faces"
    assert stub.stub.downloads == []


def test_cancel_cancels_on_the_service(stub):
    stub.stub.outcome = "running"
    task = client.Task(client.Client(stub.url), "box.obj", client.obj_bytes(CUBE, CUBE_FACES), {}, poll=0.01)
    task.start()
    deadline = time.monotonic() + 10
    while task.snapshot()["stage"] != "faces" and time.monotonic() < deadline:
        time.sleep(0.01)
    task.cancel()
    task.join(5)
    assert task.snapshot()["state"] == "cancelled" and len(stub.stub.cancelled) == 1


def test_unreachable_and_timeout(stub):
    snap, _ = run_task(client.Client(f"http://127.0.0.1:{free_port()}"), {})
    assert snap["state"] == "failed" and snap["error"] == "unreachable"
    stub.stub.slow = 1.0
    t0 = time.monotonic()
    with pytest.raises(client.ServiceError) as e:
        client.Client(stub.url, timeout=0.2).job("x")
    assert e.value.code == "timeout" and time.monotonic() - t0 < 0.9


# ------------------------------------------------------------------------------------- the real service
@pytest.fixture(scope="module")
def served(tmp_path_factory):
    from fastmesh.pipeline import Pipeline

    url, server = local_redis(DB)
    r = redis.Redis.from_url(url)
    r.flushdb()
    weights = tmp_path_factory.mktemp("weights")
    Pipeline.random("tiny", seed=0).save(str(weights))
    s = make_settings(url, "blender", weights=str(weights), api_keys=["sekrit"])
    app = ServedApp(s)
    worker = WorkerProcess(s, "blender-w", tmp_path_factory.mktemp("logs") / "w.log").wait_ready()
    yield app
    worker.stop()
    app.stop()
    r.flushdb()
    if server:
        server.stop()


@pytest.mark.redis
def test_real_service_round_trip(served):
    c = client.Client(served.url, api_key="sekrit")
    snap, _ = run_task(c, {"seed": 1, "closed": "false", "topology": None}, data=sphere_xyz(), name="ball.xyz")
    assert snap["state"] == "done", snap
    job = snap["job"]
    assert job["params"]["seed"] == 1 and job["params"]["closed"] == "false" and job["params"]["formats"] == ["glb"]
    mesh = trimesh.load(io.BytesIO(snap["result"]), file_type="glb", force="mesh")
    assert len(mesh.faces) == job["result"]["faces"]
    with pytest.raises(client.ServiceError) as e:
        c.submit("bad.ply", b"not a ply at all", {})
    assert (e.value.status, e.value.code) == (422, "unreadable")
    with pytest.raises(client.ServiceError) as e:
        c.submit("ball.xyz", sphere_xyz(), {"seed": -1})
    assert (e.value.status, e.value.code) == (422, "invalid_parameter") and "seed" in e.value.message


# ------------------------------------------------------------------------------------- the zip
def test_make_builds_the_installable_zip(tmp_path):
    out = tmp_path / "addon.zip"
    subprocess.run(["make", "-s", "blender-addon", f"BLENDER_ZIP={out}"], cwd=ROOT, check=True)
    with zipfile.ZipFile(out) as z:
        assert sorted(z.namelist()) == ["fastmesh_blender/__init__.py", "fastmesh_blender/client.py"]
        init = z.read("fastmesh_blender/__init__.py")
        assert z.read("fastmesh_blender/client.py") == (ADDON / "client.py").read_bytes()
    info = next(ast.literal_eval(n.value) for n in ast.parse(init).body
                if isinstance(n, ast.Assign) and getattr(n.targets[0], "id", "") == "bl_info")
    assert info["name"] == "FastMesh" and info["blender"] >= (3, 0, 0) and info["category"] == "Mesh"
    first = out.read_bytes()
    subprocess.run(["make", "-s", "blender-addon", f"BLENDER_ZIP={out}"], cwd=ROOT, check=True)
    assert out.read_bytes() == first  # reproducible
    assert "/build/" in (ROOT / ".gitignore").read_text().split()


# ------------------------------------------------------------------------------------- in Blender
# FASTMESH_BLENDER: another Blender, or a Python with PyPI's bpy (Blender as a module) to run the script in.
BLENDER = shutil.which(os.environ.get("FASTMESH_BLENDER", "blender"))
SCRIPT = ROOT / "tests" / "blender_addon_run.py"


@pytest.mark.skipif(BLENDER is None, reason="Blender is not installed (make test installs it: "
                                            "scripts/install-blender.sh)")
def test_addon_in_blender(stub, tmp_path):
    zip_path = tmp_path / "fastmesh_blender.zip"
    subprocess.run([sys.executable, str(ROOT / "scripts" / "blender_addon.py"), str(zip_path)], check=True)
    stub.stub.key = "sekrit"
    # A user folder of our own: installing the add-on must not touch the user's Blender set-up.
    env = {**os.environ, "BLENDER_USER_CONFIG": str(tmp_path / "config"),
           "BLENDER_USER_SCRIPTS": str(tmp_path / "scripts"), "FASTMESH_STUB": stub.url,
           "FASTMESH_ZIP": str(zip_path), "FASTMESH_GLB": str(tmp_path / "box.glb")}
    trimesh.creation.box().export(tmp_path / "box.glb")
    cmd = ([BLENDER, str(SCRIPT)] if Path(BLENDER).name.startswith("python") else
           [BLENDER, "--background", "--factory-startup", "--python-exit-code", "1", "--python", str(SCRIPT)])
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=120)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
    assert proc.returncode == 0 and lines, proc.stdout[-3000:] + proc.stderr[-3000:]
    got = json.loads(lines[-1][len("RESULT "):])
    subs = stub.stub.submissions
    assert [s["fields"] for s in subs] == [{"target_faces": "500", "origin": "bottom", "formats": "glb"},
                                           {"topology": "quad", "height": "1.8", "formats": "obj"}, {"formats": "glb"},
                                           {"seed": "13", "formats": "glb"}, {"seed": "7", "formats": "glb"},
                                           {"topology": "quad", "origin": "center", "up": "z", "uv": "true",
                                            "formats": "obj"}, {"seed": "99", "formats": "glb"}]
    # Where the glTF importer fails (Debian's Blender 3.4 with numpy 1.24) the add-on fetches the OBJ.
    glb = ["glb"] if got["gltf_works"] else ["glb", "obj"]
    assert stub.stub.downloads == glb + ["obj"] + glb + ["glb", "obj", "obj"]  # none for the failed job
    assert all(s["headers"]["Authorization"] == "Bearer sekrit" for s in subs)
    # The uploaded cube: scaled (1, 2, 3) in Blender's Z-up frame, so 2 x 6 x 4 in the file's Y-up frame.
    up = trimesh.load(io.BytesIO(subs[0]["data"]), file_type="obj", process=False)
    assert np.allclose(up.extents, [2, 6, 4]) and subs[0]["filename"] == "Cube.obj"
    # The original spans x 4..6, y -1..3, z -1..5: the result stands one width (2) along X, its pivot at the
    # original's bottom centre moved so.
    first = got["Cube_fastmesh"]
    assert np.allclose(first["min"], [6, -1, -1], atol=1e-5) and np.allclose(first["max"], [8, 3, 5], atol=1e-5)
    assert np.allclose(first["location"], [7, 1, -1], atol=1e-5)
    quads = got["Cube_fastmesh.001"]  # the second run's name: Blender numbers a taken name
    assert quads["polygon_sizes"] == [4] * 6 and np.allclose(quads["min"], [6, -1, -1], atol=1e-5)
    assert np.allclose(quads["location"], [2, 0, 0], atol=1e-5)  # origin=input: moved one width
    assert got["file"]["name"] == "box_fastmesh" and np.allclose(got["file"]["min"], [-1, -1, -1], atol=1e-5)
    assert got["failed"] == "Cube: job failed: the model made no faces"
    # A GLB the importer cannot read: the same result as OBJ, placed alike.
    assert got["fallback"]["polygon_sizes"] == [4] * 6 and np.allclose(got["fallback"]["min"], [6, -1, -1], atol=1e-5)
    # A Z-up OBJ (up=z turns OBJ files; Blender's importer turns it as Y-up) stands beside the original too,
    # its pivot one width from the original's centre.
    turned = got["Cube_fastmesh.003"]
    assert turned["polygon_sizes"] == [4] * 6 and np.allclose(turned["location"], [7, 1, 2], atol=1e-5)
    assert np.allclose(turned["min"], [6, -1, -1], atol=1e-5) and np.allclose(turned["max"], [8, 3, 5], atol=1e-5)
    assert got["target_faces_range"] == list(TARGET_FACES)
    assert got["cancelled"] == "Cube: cancelled" and len(stub.stub.cancelled) == 1
    # The panel: every setting, the job's progress and Cancel while it runs, the outcome after.
    running = [tuple(d) for d in got["drawn_running"]]
    assert [n for kind, n in running if kind == "prop"] == [
        "source", "use_target_faces", "target_faces", "use_height", "height", "use_seed", "seed", "topology",
        "origin", "up", "closed", "uv"]
    assert ("operator", "fastmesh.send") in running and ("operator", "fastmesh.cancel") in running
    assert any(n.startswith("Cube: ") and (kind == "progress" or kind == "label" and n.endswith("%)"))
               for kind, n in running), running
    assert ["label", "Cube_fastmesh: done: 8 vertices, 12 faces"] in got["drawn_done"]
    assert ["operator", "fastmesh.cancel"] not in got["drawn_done"]
