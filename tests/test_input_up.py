"""``input_up``: a Z-up input read as Z-up, through the Python API, the CLI and the HTTP form (a box 1 x 1 x 2
standing along Z, asked to stand 1.8 tall, stands 1.8 tall).  Boxes take the planar path: no network decides."""

from __future__ import annotations

import io
import json
import re
import subprocess
import sys

import httpx
import numpy as np
import pytest
import trimesh
from stack import assert_error, make_settings, post, wait_final, wp

from fastmesh.params import GenerateParams
from fastmesh.pipeline import Pipeline
from fastmesh.shapes.shape import Shape
from service.processes import ServedApp

TALL = 1.8


def z_up_box() -> trimesh.Trimesh:
    """1 x 1 x 2, standing along +Z, its foot at z = 5 (a Z-up tool's crate)."""
    box = trimesh.creation.box(extents=(1.0, 1.0, 2.0))
    box.apply_translation((0.0, 0.0, 6.0))
    return box


@pytest.fixture(scope="module")
def pipe() -> Pipeline:
    return Pipeline.random(seed=0)


def test_a_z_up_box_stands_as_tall_as_asked(pipe):
    box = z_up_box()
    shape = Shape(vertices=np.asarray(box.vertices), faces=np.asarray(box.faces))
    res = pipe.generate(shape, GenerateParams(input_up="z", height=TALL, origin="bottom"))
    assert np.allclose(np.ptp(res.vertices, axis=0), [0.9, TALL, 0.9])  # Y-up: its long side up
    assert np.isclose(res.vertices[:, 1].min(), 0.0)  # standing on the ground
    assert res.info["placement"]["scale"] == pytest.approx(0.9)
    assert res.quality["hd"] == pytest.approx(0.0, abs=1e-6)  # measured against the input as it was read
    # Read Y-up (the default), the same box lies on its side: 2 along Z, so 1.8 tall means 1.8 x 1.8 x 3.6.
    lying = pipe.generate(shape, GenerateParams(height=TALL, origin="bottom"))
    assert np.allclose(np.ptp(lying.vertices, axis=0), [TALL, TALL, 2 * TALL])
    # up=z writes the OBJ Z-up again: the box stands along Z there.
    back = pipe.generate(shape, GenerateParams(input_up="z", up="z", height=TALL, origin="bottom"))
    obj = trimesh.load(io.BytesIO(back.export("obj")), file_type="obj", force="mesh", process=False)
    assert np.allclose(np.ptp(obj.vertices, axis=0), [0.9, 0.9, TALL])


def test_a_point_cloud_is_turned_with_its_normals(pipe):
    box = z_up_box()
    pts, idx = trimesh.sample.sample_surface_even(box, 3000, seed=0)
    shape = Shape(vertices=np.asarray(pts), normals=np.asarray(box.face_normals[idx]))
    res = pipe.generate(shape, GenerateParams(input_up="z", height=TALL, origin="bottom"))
    assert np.allclose(np.ptp(res.vertices, axis=0), [0.9, TALL, 0.9], atol=0.02)


@pytest.mark.parametrize("bad", ["x", "+z", "Z", ""])
def test_a_bad_input_up_is_refused_by_name(bad):
    with pytest.raises(ValueError, match=re.escape(f"input_up must be one of y, z, got '{bad}'")):
        GenerateParams(input_up=bad).validate()


def test_cli_reads_input_up(tmp_path, weights):
    src, out = tmp_path / "crate.ply", tmp_path / "crate.obj"
    z_up_box().export(src)
    r = subprocess.run([sys.executable, "-m", "fastmesh.cli", "generate", str(src), "-o", str(out), "--weights",
                        weights, "--input-up", "z", "--height", str(TALL), "--origin", "bottom", "--json"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout.splitlines()[-1])["result_from"] in ("planes", "input")
    obj = trimesh.load(out, force="mesh", process=False)
    assert np.allclose(np.ptp(obj.vertices, axis=0), [0.9, TALL, 0.9])
    bad = subprocess.run([sys.executable, "-m", "fastmesh.cli", "generate", str(src), "-o", str(out),
                          "--input-up", "x"], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "--input-up" in bad.stderr and "'x'" in bad.stderr


@pytest.fixture(scope="module")
def served(redis_url, weights, tmp_path_factory):
    s = make_settings(redis_url, "inputup", weights=weights)
    app = ServedApp(s)
    worker = wp(s, "inputup-w", tmp_path_factory.mktemp("logs") / "w.log").wait_ready()
    yield app
    worker.stop()
    app.stop()


def test_http_form_reads_input_up_and_refuses_a_bad_one(served):
    data = io.BytesIO()
    z_up_box().export(data, file_type="ply")
    r = post(served.url, "crate.ply", data.getvalue(), input_up="z", height=TALL, origin="bottom",
             formats="glb")
    assert r.status_code == 202, r.text
    job = wait_final(served.url, r.json()["id"])
    assert job["status"] == "succeeded", job
    assert job["params"]["input_up"] == "z"
    glb = httpx.get(f"{served.url}/v1/jobs/{job['id']}/result", params={"format": "glb"}, timeout=60).content
    mesh = trimesh.load(io.BytesIO(glb), file_type="glb", force="mesh", process=False)
    assert np.allclose(np.ptp(mesh.vertices, axis=0), [0.9, TALL, 0.9])
    body = assert_error(post(served.url, "crate.ply", data.getvalue(), input_up="x"), 422)
    assert "input_up" in body["message"] and "'x'" in body["message"], body
