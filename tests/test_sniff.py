"""A file's format: told from bytes given without a name, and a text of another kind renamed to a mesh format
reported as unreadable (not as empty)."""

from __future__ import annotations

import io

import numpy as np
import pytest
import trimesh

from fastmesh.shapes.io import load_shape
from fastmesh.shapes.shape import ShapeError
from fastmesh.shapes.sniff import sniff_format

NOTE = b"Shapes for the chair project.\nAsk Ana before changing them.\n"


def _box() -> trimesh.Trimesh:
    return trimesh.creation.box(extents=(2.0, 1.0, 0.5))


def _mesh_bytes(fmt: str) -> bytes:
    if fmt == "gltf":
        return trimesh.exchange.gltf.export_gltf(trimesh.Scene(_box()), embed_buffers=True)["model.gltf"]
    if fmt == "ascii-stl":
        return trimesh.exchange.stl.export_stl_ascii(_box()).encode()
    out = _box().export(file_type=fmt)
    return out.encode() if isinstance(out, str) else out


def _array_bytes(fmt: str) -> bytes:
    points = np.random.default_rng(0).normal(size=(60, 3))
    buf = io.BytesIO()
    if fmt == "npy":
        np.save(buf, points)
    else:
        np.savez(buf, points=points)
    return buf.getvalue()


@pytest.mark.parametrize("fmt, sniffed", [("obj", "obj"), ("glb", "glb"), ("gltf", "gltf"), ("ply", "ply"),
                                          ("stl", "stl"), ("ascii-stl", "stl"), ("off", "off")])
def test_mesh_bytes_without_a_name_are_read_by_their_content(fmt, sniffed):
    data = _mesh_bytes(fmt)
    assert sniff_format(data) == sniffed
    shape = load_shape(data)
    assert len(shape.faces) == 12 and np.allclose(shape.bounds, _box().bounds, atol=1e-6)


@pytest.mark.parametrize("fmt", ["npy", "npz", "xyz", "ply"])
def test_point_bytes_without_a_name_are_read_by_their_content(fmt):
    points = np.random.default_rng(0).normal(size=(60, 3))
    if fmt == "xyz":
        data = b"# x y z\n\n" + "\n".join(f"{x:.6f}, {y:.6f}, {z:.6f}" for x, y, z in points).encode()
    elif fmt == "ply":
        data = trimesh.PointCloud(points).export(file_type="ply")
    else:
        data = _array_bytes(fmt)
    shape = load_shape(data)
    assert shape.kind == "points" and len(shape.vertices) == 60 and shape.normals.shape == (60, 3)
    assert np.allclose(shape.vertices, points, atol=1e-5)


@pytest.mark.parametrize("data", [NOTE, b"\x00\x01\x02 binary of some kind", b"1 2\n3 4\n", b"# only a comment\n"])
def test_bytes_whose_content_does_not_say_ask_for_a_name(data):
    assert sniff_format(data) is None
    with pytest.raises(ShapeError) as e:
        load_shape(data)
    assert e.value.code == "unsupported_format"
    assert "cannot tell the format of these bytes" in e.value.message and "filename='shape.obj'" in e.value.message
    assert "'.'" not in e.value.message


def test_empty_bytes_without_a_name_are_empty_and_a_name_without_extension_is_said():
    with pytest.raises(ShapeError) as e:
        load_shape(b"")
    assert e.value.code == "empty"
    with pytest.raises(ShapeError) as e:
        load_shape(_mesh_bytes("obj"), filename="chair")
    assert e.value.code == "unsupported_format" and e.value.message.startswith("'chair' has no extension")


@pytest.mark.parametrize("name, data, start", [
    ("notes.obj", NOTE, "not a Wavefront OBJ file: line 1 starts with 'Shapes', not an OBJ statement"),
    ("notes.stl", NOTE * 3, "not an STL file: it does not start with 'solid' (ASCII STL) and does not have the "
                            "length its binary header declares"),
    ("notes.stl", NOTE, "not an STL file: it does not start with 'solid' (ASCII STL) and is 60 bytes, shorter"),
])
def test_a_text_renamed_to_a_mesh_format_is_unreadable(name, data, start):
    with pytest.raises(ShapeError) as e:
        load_shape(data, filename=name)
    assert e.value.code == "unreadable" and e.value.message.startswith(start), e.value.message


def test_obj_and_stl_without_geometry_are_still_empty():
    for data, name in ((b"# exported by a tool\no empty\ng nothing\n", "x.obj"), (b"solid x\nendsolid x\n", "x.stl")):
        with pytest.raises(ShapeError) as e:
            load_shape(data, filename=name)
        assert e.value.code == "empty", (name, e.value.message)


def test_a_binary_stl_declaring_more_triangles_than_the_limit_is_refused_before_parsing():
    data = _mesh_bytes("stl")
    assert len(load_shape(data, filename="box.stl").faces) == 12
    with pytest.raises(ShapeError) as e:
        load_shape(data, filename="box.stl", max_faces=11)
    assert e.value.code == "too_large" and "12 faces exceed the limit of 11" in e.value.message
