"""origin, height and up (fastmesh.export.placement) through the Python API and the CLI, checked on the bounds of the
files written; the CLI's --topology, --uv and --bake."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
import trimesh
from test_quads import read_obj, read_ply
from test_uv_layout import glb_json, textured_box_glb

from fastmesh.cli import main
from fastmesh.export import layout
from fastmesh.export.placement import placement, turn_up
from fastmesh.params import GenerateParams
from fastmesh.pipeline import Pipeline
from fastmesh.shapes.shape import Shape

CENTER, EXTENTS = np.array([5.0, -2.0, 1.0]), np.array([1.0, 2.0, 3.0])  # the box: x 4.5..5.5, y -3..-1, z -0.5..2.5


@pytest.fixture(scope="module")
def pipe():
    return Pipeline.random("tiny", seed=0)


def box() -> Shape:
    b = trimesh.creation.box(extents=EXTENTS)
    return Shape(vertices=np.asarray(b.vertices) + CENTER, faces=np.asarray(b.faces))


def bounds(fmt: str, data: bytes) -> np.ndarray:
    if fmt == "glb":
        v = trimesh.load(io.BytesIO(data), file_type="glb", force="mesh", process=False).vertices
    else:
        v = read_obj(data)[0] if fmt == "obj" else read_ply(data)[0]
    return np.stack([v.min(axis=0), v.max(axis=0)])


@pytest.mark.parametrize("origin, height, expected", [
    ("input", None, [[4.5, -3, -0.5], [5.5, -1, 2.5]]),
    ("center", None, [[-0.5, -1, -1.5], [0.5, 1, 1.5]]),
    ("bottom", None, [[-0.5, 0, -1.5], [0.5, 2, 1.5]]),
    ("bottom", 1.8, [[-0.45, 0, -1.35], [0.45, 1.8, 1.35]]),
    ("input", 4.0, [[9, -6, -1], [11, -2, 5]]),  # scaled about the input's own origin
])
def test_origin_and_height_on_every_format(pipe, origin, height, expected):
    res = pipe.generate(box(), GenerateParams(origin=origin, height=height, topology="quad"))
    for fmt in ("glb", "obj", "ply"):
        assert np.allclose(bounds(fmt, res.export(fmt)), expected, atol=1e-5), fmt
    where = res.info["placement"]
    assert np.allclose(box().vertices.min(0) * where["scale"] + where["offset"], expected[0])
    assert res.quality["cd"] == 0 and res.quality["quad_share"] == 1.0  # measured in the input's frame


def test_up_z_turns_obj_and_ply_but_not_glb(pipe):
    res = pipe.generate(box(), GenerateParams(origin="bottom", height=1.8, up="z", uv=True))
    y_up = [[-0.45, 0, -1.35], [0.45, 1.8, 1.35]]
    z_up = [[-0.45, -1.35, 0], [0.45, 1.35, 1.8]]  # (x, y, z) -> (x, -z, y): stands 1.8 along +Z
    assert np.allclose(bounds("glb", res.export("glb")), y_up, atol=1e-5)
    assert np.allclose(bounds("obj", res.export("obj")), z_up, atol=1e-5)
    assert np.allclose(bounds("ply", res.export("ply")), z_up, atol=1e-5)
    assert any("GLB stays Y-up" in n for n in res.info["notes"]) and res.info["placement"]["up"] == "z"
    # A right-handed turn: the faces still face outwards (the OBJ's volume is positive).
    v, faces, _, _ = read_obj(res.export("obj"))
    assert trimesh.Trimesh(v, faces, process=False).volume == pytest.approx(0.9 * 1.8 * 2.7, rel=1e-6)


def test_placement_refuses_what_it_cannot_do():
    flat = np.array([[0, 0, 0], [1, 0, 0], [0, 0, 1.0]])
    assert placement(flat, "bottom").scale == 1.0
    with pytest.raises(ValueError, match="height: the result is flat"):
        placement(flat, "input", height=2.0)
    assert np.allclose(turn_up(np.array([[1.0, 2.0, 3.0]]), "z"), [[1, -3, 2]])
    for bad, match in ((dict(origin="top"), "origin must be one of input, center, bottom"),
                       (dict(up="x"), "up must be one of y, z"), (dict(topology="quads"), "topology"),
                       (dict(height=0.0), "height must be in"), (dict(height=1e6), "height must be in"),
                       (dict(bake=True), "bake needs uv=true")):
        with pytest.raises(ValueError, match=match):
            GenerateParams(**bad).validate()


def _cli(capsys, *argv) -> tuple[int, list[dict], str]:
    code = main([str(a) for a in argv])
    out = capsys.readouterr()
    return code, [json.loads(line) for line in out.out.splitlines() if line.startswith("{")], out.err


def test_cli_quads_uv_and_placement(capsys, tmp_path, weights):
    src, out = tmp_path / "box.obj", tmp_path / "out.obj"
    trimesh.Trimesh(box().vertices, box().faces).export(src)
    code, recs, err = _cli(capsys, "generate", src, "-o", out, "--weights", weights, "--topology", "quad", "--uv",
                           "--origin", "bottom", "--height", "2", "--up", "z", "--json")
    assert code == 0, err
    rec = recs[0]
    assert rec["quality"]["quads"] == 6 and rec["quality"]["quad_share"] == 1.0
    assert rec["placement"] == {"scale": 1.0, "offset": [-5.0, 3.0, -1.0], "up": "z"}
    assert "6 quads (100 % of the polygons)" in err and "note: GLB holds triangles" in err
    v, faces, vt, face_uv = read_obj(out.read_bytes())
    assert [len(f) for f in faces] == [4] * 6 and len(face_uv) == 6 and vt.min() >= 0 and vt.max() <= 1
    assert np.allclose([v.min(0), v.max(0)], [[-0.5, -1.5, 0], [0.5, 1.5, 2]], atol=1e-6)
    code, _, err = _cli(capsys, "generate", src, "-o", tmp_path / "x.glb", "--weights", weights, "--bake")
    assert code == 2 and "bake needs uv=true" in err
    with pytest.raises(SystemExit) as e:
        main(["generate", str(src), "-o", str(tmp_path / "x.glb"), "--topology", "quads"])
    assert e.value.code == 2 and "invalid choice: 'quads'" in capsys.readouterr().err


def test_cli_bake(capsys, tmp_path, weights, monkeypatch):
    monkeypatch.setattr(layout, "TEXTURE_SIZE", 256)  # the same steps on fewer texels
    src, out = tmp_path / "box.glb", tmp_path / "baked.glb"
    src.write_bytes(textured_box_glb())
    code, recs, err = _cli(capsys, "generate", src, "-o", out, "--weights", weights, "--uv", "--bake", "--json")
    assert code == 0, err
    doc = glb_json(out.read_bytes())
    assert "baseColorTexture" in doc["materials"][0]["pbrMetallicRoughness"]
    mesh = trimesh.load(out, force="mesh", process=False)
    assert mesh.visual.material.baseColorTexture.size == (256, 256)
    assert not any("no base-colour texture" in n for n in recs[0]["notes"])
