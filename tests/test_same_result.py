"""One file and one set of parameters give one mesh, whichever interface runs them: ``fastmesh generate``, the
Python API, and the service (a real Redis, the API, a ``fastmesh-worker`` process).

The decoder samples vertices one cell at a time: a coordinate moved by 1e-8 on its way to a worker can change
which cell wins, and from there the whole mesh.  So the comparison is exact, in float64 where the interface
gives float64 (the Python API, the worker's stored result) and byte for byte in the files each one writes.
"""

from __future__ import annotations

import subprocess
import sys

import httpx
import numpy as np
import pytest
import trimesh
from stack import DB, forget_run, make_settings, post, sphere_points, wait_final, wp, xyz_bytes
from testdata import committed_meshes

from fastmesh.pipeline import GenerateParams, Pipeline
from fastmesh.shapes.io import load_shape
from fastmesh_jobs.blobs import mesh_from_bytes
from fastmesh_jobs.store import Store
from service.processes import ServedApp, local_redis

PARAMS = {"seed": 3, "max_vertices": 20}


@pytest.fixture(scope="module")
def service(weights, tmp_path_factory):
    url, server = local_redis(DB)
    settings = make_settings(url, "same", weights=weights)
    app = ServedApp(settings)
    worker = wp(settings, "same-w", tmp_path_factory.mktemp("logs") / "w.log").wait_ready()
    yield app
    worker.stop()
    app.stop()
    forget_run(url)
    if server:
        server.stop()


def _chicken(directory):
    """The issue's mesh: an artist mesh already low-poly, which comes back as it is (welded)."""
    return next(p for p in committed_meshes() if "chicken" in p.name)


def _far_cloud(directory):
    """A point cloud in text far from the origin, for the networks: its coordinates are no float32 numbers."""
    path = directory / "far.xyz"
    path.write_bytes(xyz_bytes(sphere_points(600, seed=4, center=(1234.5, -77.25, 3.0)) * 1.7, fmt="%.9f"))
    return path


def _dense_mesh(directory):
    """A mesh in OBJ text, turned and scaled: its coordinates are no float32 numbers either."""
    mesh = trimesh.creation.icosphere(3)
    mesh.apply_transform(trimesh.transformations.rotation_matrix(0.7, [1.0, 2.0, 0.5]))
    mesh.apply_scale([31.3, 20.1, 17.9])
    path = directory / "dense.obj"
    mesh.export(path)
    return path


@pytest.mark.parametrize("make", [_chicken, _far_cloud, _dense_mesh], ids=["chicken-ply", "far-xyz", "dense-obj"])
def test_cli_python_api_and_service_give_the_same_mesh(service, weights, tmp_path, make):
    src = make(tmp_path)
    data = src.read_bytes()

    r = post(service.url, src.name, data, formats="ply", **PARAMS)
    assert r.status_code == 202, r.text
    job = wait_final(service.url, r.json()["id"], timeout=120)
    assert job["status"] == "succeeded", job
    served_ply = httpx.get(f"{service.url}/v1/jobs/{job['id']}/result", params={"format": "ply"}, timeout=30).content
    served_v, served_f = mesh_from_bytes(Store(service.settings).get_result(job["id"], "npz"))

    result = Pipeline.from_pretrained(weights).generate(load_shape(src), GenerateParams(**PARAMS))

    out = tmp_path / "cli.ply"
    cli = subprocess.run([sys.executable, "-m", "fastmesh.cli", "generate", str(src), "-o", str(out),
                          "--weights", weights, "--seed", str(PARAMS["seed"]),
                          "--max-vertices", str(PARAMS["max_vertices"])],
                         capture_output=True, text=True, timeout=300)
    assert cli.returncode == 0, cli.stderr

    assert served_v.dtype == np.float64 and result.vertices.dtype == np.float64
    assert np.array_equal(served_f, result.faces) and np.array_equal(served_v, result.vertices), (
        f"service {len(served_v)} V / {len(served_f)} F, Python API {len(result.vertices)} V / "
        f"{len(result.faces)} F, largest vertex difference "
        f"{np.abs(served_v - result.vertices).max() if served_v.shape == result.vertices.shape else 'n/a'}")
    assert job["result"]["seed"] == result.info.get("chosen_seed")
    assert served_ply == result.export("ply") == out.read_bytes()
