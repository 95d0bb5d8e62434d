"""topology, uv, bake, origin, height and up through the HTTP API: a real app, Redis and a ``fastmesh-worker``
with the tiny random model (closed, flat-sided inputs take the planar path, so the networks never decide)."""

from __future__ import annotations

import io
import json

import httpx
import numpy as np
import pytest
import trimesh
from stack import assert_error, make_settings, post, wait_final, wp
from test_quads import read_obj, read_ply
from test_uv_layout import COLOURS, glb_json, side_of, textured_box_glb

from fastmesh.export.bake import sample
from fastmesh.export.layout import overlap_share
from service.processes import ServedApp


@pytest.fixture(scope="module")
def served(redis_url, weights, tmp_path_factory):
    s = make_settings(redis_url, "retopo", weights=weights)
    app = ServedApp(s)
    worker = wp(s, "retopo-w", tmp_path_factory.mktemp("logs") / "w.log").wait_ready()
    yield app
    worker.stop()
    app.stop()


def result(app, job_id: str, fmt: str) -> bytes:
    r = httpx.get(f"{app.url}/v1/jobs/{job_id}/result", params={"format": fmt}, timeout=60)
    assert r.status_code == 200, r.text
    return r.content


def test_quads_uv_bake_and_placement_over_http(served):
    app = served
    r = post(app.url, "crate.glb", textured_box_glb(center=(3.0, 1.0, -2.0), size=2.0), topology="quad",
             uv="true", bake="true", origin="bottom", height="0.5", up="z", formats="glb,obj")
    assert r.status_code == 202, r.text
    job = wait_final(app.url, r.json()["id"])
    assert job["status"] == "succeeded", job
    assert {k: job["params"][k] for k in ("topology", "uv", "bake", "origin", "height", "up")} == {
        "topology": "quad", "uv": True, "bake": True, "origin": "bottom", "height": 0.5, "up": "z"}
    res = job["result"]
    assert res["quality"]["quads"] == 6 and res["quality"]["quad_share"] == 1.0
    assert res["placement"] == {"scale": 0.25, "offset": [-0.75, 0.0, 0.5], "up": "z"}
    notes = " ".join(res["notes"])
    assert "GLB holds triangles" in notes and "GLB stays Y-up" in notes and "no base-colour texture" not in notes

    glb = result(app, job["id"], "glb")
    assert "TEXCOORD_0" in glb_json(glb)["meshes"][0]["primitives"][0]["attributes"]
    mesh = trimesh.load(io.BytesIO(glb), file_type="glb", force="mesh", process=False)
    assert len(mesh.faces) == 12 and np.allclose(mesh.bounds, [[-0.25, 0, -0.25], [0.25, 0.5, 0.25]])
    assert overlap_share(mesh.visual.uv, mesh.faces) < 1e-3
    baked = np.asarray(mesh.visual.material.baseColorTexture.convert("RGBA"))
    for f, normal in zip(mesh.faces, mesh.face_normals, strict=True):  # the texture came through the upload
        got = sample(baked, mesh.visual.uv[f].mean(axis=0, keepdims=True))[0, :3]
        assert np.abs(got - COLOURS[side_of(normal)]).max() <= 2

    v, faces, vt, face_uv = read_obj(result(app, job["id"], "obj"))
    assert [len(f) for f in faces] == [4] * 6 and len(face_uv) == 6 and vt.min() >= 0 and vt.max() <= 1
    assert np.allclose([v.min(0), v.max(0)], [[-0.25, -0.25, 0], [0.25, 0.25, 0.5]], atol=1e-6)  # Z up
    # PLY was not exported with the job: made on request from the stored result, quads and turn included.
    v, faces = read_ply(result(app, job["id"], "ply"))
    assert [len(f) for f in faces] == [4] * 6
    assert np.allclose([v.min(0), v.max(0)], [[-0.25, -0.25, 0], [0.25, 0.25, 0.5]], atol=1e-6)


def test_defaults_keep_todays_result(served):
    app = served
    box = trimesh.creation.box(extents=(1, 2, 3))
    box.apply_translation([5, -2, 1])
    r = post(app.url, "box.obj", box.export(file_type="obj").encode(), formats="obj")
    job = wait_final(app.url, r.json()["id"])
    assert job["params"]["topology"] == "triangle" and job["params"]["origin"] == "input"
    assert job["params"]["uv"] is False and job["params"]["height"] is None and job["params"]["up"] == "y"
    assert job["result"]["quality"]["quad_share"] == 0.0 and job["result"]["notes"] == []
    v, faces, vt, _ = read_obj(result(app, job["id"], "obj"))
    assert {len(f) for f in faces} == {3} and len(vt) == 0
    assert np.allclose([v.min(0), v.max(0)], box.bounds)


@pytest.mark.parametrize("fields, name", [
    ({"topology": "quads"}, "topology"), ({"origin": "top"}, "origin"), ({"up": "x"}, "up"),
    ({"height": "0"}, "height"), ({"height": "1e9"}, "height"), ({"height": "tall"}, "height"),
    ({"uv": "yes"}, "uv"), ({"bake": "true"}, "bake"), ({"pivot": "bottom"}, "pivot"),
])
def test_bad_values_are_422_naming_the_field(served, fields, name):
    box = trimesh.creation.box().export(file_type="obj").encode()
    err = assert_error(post(served.url, "box.obj", box, **fields), 422)
    assert name in err["message"], err


def test_a_batch_takes_the_same_fields(served):
    box = trimesh.creation.box().export(file_type="obj").encode()
    r = httpx.post(f"{served.url}/v1/batches", files=[("files", ("a.obj", box)), ("files", ("b.obj", box))],
                   data={"topology": "quad", "origin": "center", "formats": "ply"}, timeout=60)
    assert r.status_code == 202, r.text
    for job_id in r.json()["job_ids"]:
        job = wait_final(served.url, job_id)
        assert job["result"]["quality"]["quad_share"] == 1.0
        assert [len(f) for f in read_ply(result(served, job_id, "ply"))[1]] == [4] * 6


def test_cli_submit_and_the_python_client(served, tmp_path, capsys):
    from fastmesh.cli import main
    from fastmesh.remote.client import Client

    src = tmp_path / "crate.obj"
    src.write_bytes(trimesh.creation.box(extents=(1, 2, 3)).export(file_type="obj").encode())
    out = tmp_path / "crate_quads.obj"
    code = main(["submit", str(src), "--url", served.url, "-o", str(out), "--topology", "quad", "--uv",
                 "--origin", "bottom", "--height", "1", "--up", "z", "-q", "--json"])
    assert code == 0, capsys.readouterr().err
    job = json.loads(capsys.readouterr().out)
    assert job["params"]["topology"] == "quad" and job["params"]["height"] == 1.0 and job["params"]["uv"] is True
    v, faces, vt, _ = read_obj(out.read_bytes())
    assert [len(f) for f in faces] == [4] * 6 and len(vt)
    assert np.allclose([v.min(0), v.max(0)], [[-0.25, -0.75, 0], [0.25, 0.75, 1]], atol=1e-6)
    with Client(served.url) as client:
        job = client.wait(client.submit(src, topology="quad", origin="center", uv=False, formats="ply")["id"])
    assert job["result"]["quality"]["quad_share"] == 1.0 and job["result"]["placement"]["offset"] == [0, 0, 0]
    assert job["result"]["result_from"] == "input"  # a box of 12 faces comes back as it is
    assert job["result"]["vertices_from"] == "input"
