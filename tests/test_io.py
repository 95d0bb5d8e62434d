"""Loading meshes and point clouds, normalisation, sampling, export, and clear errors."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
import trimesh

from fastmesh.shapes.io import export_mesh, load_shape, sample_surface, write_mesh
from fastmesh.shapes.shape import EXPORT_FORMATS, Normalization, Shape, ShapeError


def _box():
    return trimesh.creation.box(extents=(2.0, 1.0, 0.5))


def _mesh_bytes(fmt: str) -> bytes:
    m = _box()
    if fmt == "gltf":  # one self-contained .gltf (buffers as data URIs)
        files = trimesh.exchange.gltf.export_gltf(trimesh.Scene(m), embed_buffers=True)
        return files["model.gltf"]
    out = m.export(file_type=fmt)
    return out.encode() if isinstance(out, str) else out


@pytest.mark.parametrize("fmt", ["obj", "glb", "gltf", "ply", "stl", "off"])
def test_load_mesh_formats(fmt, tmp_path):
    data = _mesh_bytes(fmt)
    s = load_shape(data, filename=f"box.{fmt}")
    assert s.kind == "mesh" and s.normals is None
    assert s.faces.shape[1] == 3 and len(s.faces) == 12
    assert np.allclose(s.bounds[1] - s.bounds[0], [2.0, 1.0, 0.5], atol=1e-5)
    p = tmp_path / f"box.{fmt.upper()}"  # extensions are case-insensitive
    p.write_bytes(data)
    assert len(load_shape(p).faces) == 12


def test_load_point_cloud_formats(tmp_path):
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(200, 3))
    nrm = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    # PLY without faces, with normals
    pc = trimesh.PointCloud(pts)
    ply = trimesh.exchange.ply.export_ply(pc, vertex_normal=False)
    s = load_shape(ply, filename="cloud.ply")
    assert s.kind == "points" and len(s.vertices) == 200 and s.normals.shape == (200, 3)
    header = "ply\nformat ascii 1.0\nelement vertex 200\nproperty float x\nproperty float y\nproperty float z\n" \
             "property float nx\nproperty float ny\nproperty float nz\nend_header\n"
    body = "\n".join(" ".join(f"{x:.6f}" for x in row) for row in np.hstack([pts, nrm]))
    s = load_shape((header + body + "\n").encode(), filename="cloud.ply")
    assert s.kind == "points" and np.allclose(s.normals, nrm, atol=1e-5)  # ASCII PLY normals are kept
    rec = np.zeros(200, dtype=[(k, "<f4") for k in ("x", "y", "z", "nx", "ny", "nz")])
    for i, k in enumerate("xyz"):
        rec[k], rec["n" + k] = pts[:, i], nrm[:, i]
    binary = header.replace("ascii", "binary_little_endian").encode() + rec.tobytes()
    s = load_shape(binary, filename="cloud.ply")
    assert s.kind == "points" and np.allclose(s.normals, nrm, atol=1e-5)  # binary PLY normals too
    # xyz with 3 columns (normals estimated) and txt with 6 columns (normals kept, unit length)
    (tmp_path / "c.xyz").write_text("\n".join(" ".join(f"{x:.6f}" for x in p) for p in pts))
    s = load_shape(tmp_path / "c.xyz")
    assert np.allclose(np.linalg.norm(s.normals, axis=1), 1.0)
    outward = (s.normals * (s.vertices - s.vertices.mean(0))).sum(1)
    assert (outward > 0).mean() > 0.9  # estimated normals of a blob point outward
    txt = "# comment\n" + "\n".join(", ".join(f"{x:.6f}" for x in row) for row in np.hstack([pts, 2 * nrm]))
    s = load_shape(txt.encode(), filename="c.txt")
    assert np.allclose(s.normals, nrm, atol=1e-5)
    # npy N x 3 and N x 6, npz with points + normals
    buf = io.BytesIO()
    np.save(buf, pts.astype(np.float32))
    assert load_shape(buf.getvalue(), filename="c.npy").kind == "points"
    buf = io.BytesIO()
    np.save(buf, np.hstack([pts, nrm]))
    assert np.allclose(load_shape(buf.getvalue(), filename="c.npy").normals, nrm)
    buf = io.BytesIO()
    np.savez(buf, points=pts, normals=nrm)
    assert np.allclose(load_shape(buf.getvalue(), filename="c.npz").normals, nrm)


def test_normalization_round_trip():
    rng = np.random.default_rng(1)
    v = rng.uniform([-3, 10, 0], [5, 12, 0.1], size=(500, 3))
    n = Normalization.fit(v)
    u = n.apply(v)
    assert np.allclose(u.max(0) - u.min(0), np.array([8, 2, 0.1]) / 8, atol=1e-2)
    assert u.min() >= -0.5 - 1e-12 and u.max() <= 0.5 + 1e-12
    assert np.allclose((u.max(0) + u.min(0)) / 2, 0, atol=1e-12)
    assert np.allclose(n.invert(u), v, atol=1e-12)
    d = n.to_dict()
    assert json.loads(json.dumps(d)) == d


def test_sampling_is_seeded_and_on_surface():
    s = load_shape(_mesh_bytes("ply"), filename="b.ply")
    p1, n1 = sample_surface(s, 1000, seed=3)
    p2, _ = sample_surface(s, 1000, seed=3)
    p3, _ = sample_surface(s, 1000, seed=4)
    assert np.array_equal(p1, p2) and not np.array_equal(p1, p3)
    assert p1.shape == (1000, 3) and np.allclose(np.linalg.norm(n1, axis=1), 1, atol=1e-5)
    half = np.array([1.0, 0.5, 0.25])
    on_face = np.isclose(np.abs(p1), half, atol=1e-5).any(1)
    assert on_face.all()


@pytest.mark.parametrize("fmt", EXPORT_FORMATS)
def test_export_round_trip(fmt, tmp_path):
    m = _box()
    data = export_mesh(m.vertices, m.faces, fmt)
    s = load_shape(data, filename=f"out.{fmt}")
    assert len(s.faces) == 12 and np.allclose(s.bounds, m.bounds, atol=1e-6)
    write_mesh(tmp_path / f"o.{fmt}", m.vertices, m.faces)
    assert len(load_shape(tmp_path / f"o.{fmt}").faces) == 12


def _code(source, filename=None, **kw) -> str:
    with pytest.raises(ShapeError) as e:
        load_shape(source, filename=filename, **kw)
    assert e.value.message and str(e.value)
    return e.value.code


def test_errors(tmp_path):
    assert _code(b"", "x.obj") == "empty"
    assert _code(b"v 0 0 0\n", "x.dae") == "unsupported_format"
    assert _code(tmp_path / "missing.ply") == "unreadable"
    assert _code(b"\x00\x01garbage" * 10, "x.glb") == "unreadable"
    assert _code(b"1 2\n3 4\n", "x.xyz") == "unreadable"
    assert _code(b"0 0 0\nnan 1 1\n1 0 0\n0 1 0\n", "x.xyz") == "non_finite"
    assert _code(b"1 1 1\n1 1 1\n1 1 1\n1 1 1\n", "x.xyz") == "degenerate"  # all points coincide
    assert _code(b"0 0 0\n1 1 1\n2 2 2\n3 3 3\n", "x.xyz") == "degenerate"  # collinear
    assert _code(b"0 0 0\n1 0 0\n", "x.xyz") == "degenerate"  # too few points
    flat = b"v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n"  # the only face has zero area
    assert _code(flat, "x.obj") == "degenerate"
    buf = io.BytesIO()
    np.save(buf, np.zeros((5, 4)))
    assert _code(buf.getvalue(), "x.npy") == "unreadable"
    pts = "\n".join(f"{i} {i % 7} {i % 3}" for i in range(50)).encode()
    assert _code(pts, "x.xyz", max_points=10) == "too_large"
    with pytest.raises(ShapeError):
        export_mesh(np.eye(3), np.array([[0, 1, 2]]), "fbx")


def test_pickled_npy_is_refused():
    buf = io.BytesIO()
    np.save(buf, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    assert _code(buf.getvalue(), "x.npy") == "unreadable"


def test_shape_kind():
    assert Shape(vertices=np.zeros((3, 3)), faces=np.array([[0, 1, 2]])).kind == "mesh"
    assert Shape(vertices=np.zeros((3, 3))).kind == "points"
