"""The `fastmesh tokens`, `fastmesh metrics` and `fastmesh data` verbs, including error exits."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from testdata import committed_meshes

from fastmesh.cli import main

SMALL = committed_meshes()[:2]


def _run(capsys, *argv) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture()
def meshes(tmp_path) -> Path:
    d = tmp_path / "m"
    (d / "sub").mkdir(parents=True)
    (d / "sphere.obj").write_text(trimesh.creation.icosphere(subdivisions=2).export(file_type="obj"))
    (d / "sub" / "box.ply").write_bytes(trimesh.creation.box().export(file_type="ply"))
    return d


def test_tokens_json_on_corpus_files(capsys):
    code, out, err = _run(capsys, "tokens", *SMALL, "--json")
    assert code == 0 and err == ""
    doc = json.loads(out)  # one JSON object
    assert len(doc["meshes"]) == 2
    tot = doc["total"]
    for k in ("vanilla", "bpt", "fastmesh", "vertices", "faces"):
        assert tot[k] == sum(m[k] for m in doc["meshes"])
    assert tot["ratio_fastmesh_bpt"] == pytest.approx(tot["fastmesh"] / tot["bpt"])
    for m in doc["meshes"]:
        assert m["vanilla"] == 9 * m["faces"] + 2 and m["fastmesh"] < m["bpt"] < m["vanilla"]


def test_tokens_directory_text(capsys, meshes):
    code, out, _ = _run(capsys, "tokens", meshes)
    assert code == 0
    assert "sphere.obj" in out and "box.ply" in out and "fastmesh/bpt" in out
    assert "total (2 meshes, 0 failed)" in out


def test_tokens_directory_with_failures(capsys, meshes):
    (meshes / "broken.obj").write_text("this is not a mesh\n")
    (meshes / "cloud.ply").write_bytes(trimesh.PointCloud(np.random.default_rng(0).random((50, 3))).export(
        file_type="ply"))
    code, out, err = _run(capsys, "tokens", meshes, "--json")
    assert code == 1  # failures are reported and counted, the rest still measured
    doc = json.loads(out)
    assert doc["total"]["meshes"] == 2 and doc["total"]["failed"] == 2
    assert "broken.obj" in err and "cloud.ply" in err and "point cloud" in err
    assert {Path(f["file"]).name for f in doc["failed"]} == {"broken.obj", "cloud.ply"}


def test_tokens_errors(capsys, tmp_path):
    code, _, err = _run(capsys, "tokens", tmp_path / "missing.obj")
    assert code == 1 and "missing.obj" in err
    (tmp_path / "empty").mkdir()
    code, _, err = _run(capsys, "tokens", tmp_path / "empty")
    assert code == 2 and "no mesh files" in err
    (tmp_path / "x.dae").write_text("<COLLADA/>")
    code, _, err = _run(capsys, "tokens", tmp_path / "x.dae")
    assert code == 1 and "unsupported" in err


def test_metrics(capsys, meshes, tmp_path):
    sphere, box = meshes / "sphere.obj", meshes / "sub" / "box.ply"
    code, out, _ = _run(capsys, "metrics", sphere, sphere, "--json")
    assert code == 0 and json.loads(out) == {"cd": 0.0, "hd": 0.0}
    code, out, _ = _run(capsys, "metrics", sphere, box, "--json")
    d = json.loads(out)
    assert code == 0 and 0 < d["cd"] < d["hd"] < 50
    code, out, _ = _run(capsys, "metrics", sphere, box)
    assert code == 0 and "CD" in out and "HD" in out
    code, _, err = _run(capsys, "metrics", sphere, tmp_path / "missing.ply")
    assert code == 2 and "missing.ply" in err and "Traceback" not in err
    (tmp_path / "nan.xyz").write_text("0 0 0\nnan 0 0\n1 1 1\n0 1 0\n")
    code, _, err = _run(capsys, "metrics", tmp_path / "nan.xyz", sphere)
    assert code == 2 and "NaN" in err


def test_data_build_and_stats(capsys, meshes, tmp_path):
    out = tmp_path / "cache.npz"
    code, text, _ = _run(capsys, "data", "build", meshes, "-o", out, "--workers", "1")
    assert code == 0 and json.loads(text)["meshes"] == 2 and out.exists()
    code, text, _ = _run(capsys, "data", "stats", out)
    assert code == 0 and json.loads(text)["meshes"] == 2
    code, _, err = _run(capsys, "data", "build", tmp_path / "nope", "-o", tmp_path / "y.npz")
    assert code == 2 and "nope" in err
    code, _, err = _run(capsys, "data", "build", meshes, "-o", tmp_path / "y.npz", "--max-vertices", "2")
    assert code == 2 and "max-vertices" in err


def test_console_entry_point_subprocess():
    cmd = [sys.executable, "-c", "import sys; from fastmesh.cli import main; sys.exit(main())", "tokens", str(SMALL[0]),
           "--json"]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert json.loads(p.stdout)["total"]["meshes"] == 1
