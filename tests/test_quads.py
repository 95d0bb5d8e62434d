"""topology=quad: triangles paired into quads (fastmesh.export.quads), written as 4-corner faces to OBJ and PLY by
fastmesh.export.meshfiles, read back here by parsers of the tests' own."""

from __future__ import annotations

import io

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from fastmesh.export.output import MeshOut
from fastmesh.export.quads import QuadConfig, interior_pairs, pair_triangles, quad_corners, quad_share
from fastmesh.params import GenerateParams
from fastmesh.pipeline import Pipeline
from fastmesh.shapes.shape import Shape


@pytest.fixture(scope="module")
def pipe():
    return Pipeline.random("tiny", seed=0)


def read_obj(data: bytes) -> tuple[np.ndarray, list[list[int]], np.ndarray, list[list[int]]]:
    """(vertices, faces as 0-based corner lists, vt rows, faces' vt corner lists) of an OBJ."""
    v, vt, faces, face_uv = [], [], [], []
    for line in data.decode().splitlines():
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "v":
            v.append([float(x) for x in parts[1:4]])
        elif parts[0] == "vt":
            vt.append([float(x) for x in parts[1:3]])
        elif parts[0] == "f":
            corners = [p.split("/") for p in parts[1:]]
            faces.append([int(c[0]) - 1 for c in corners])
            if len(corners[0]) > 1 and corners[0][1]:
                face_uv.append([int(c[1]) - 1 for c in corners])
    return np.array(v), faces, np.array(vt).reshape(-1, 2), face_uv


def read_ply(data: bytes) -> tuple[np.ndarray, list[list[int]]]:
    """(vertices, faces) of a binary little-endian PLY with float x, y, z and uchar/int face lists."""
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode().splitlines()
    assert "format binary_little_endian 1.0" in header
    n_v = int(next(h for h in header if h.startswith("element vertex")).split()[-1])
    n_f = int(next(h for h in header if h.startswith("element face")).split()[-1])
    v = np.frombuffer(data, "<f4", count=3 * n_v, offset=end).reshape(-1, 3)
    pos, faces = end + 12 * n_v, []
    for _ in range(n_f):
        k = data[pos]
        faces.append(np.frombuffer(data, "<i4", count=k, offset=pos + 1).tolist())
        pos += 1 + 4 * k
    assert pos == len(data)
    return v.astype(np.float64), faces


def fan(faces: list[list[int]]) -> np.ndarray:
    return np.array([[f[0], f[i], f[i + 1]] for f in faces for i in range(1, len(f) - 1)])


def area(v: np.ndarray, tri: np.ndarray) -> float:
    return float(0.5 * np.linalg.norm(np.cross(v[tri[:, 1]] - v[tri[:, 0]], v[tri[:, 2]] - v[tri[:, 0]]), axis=1).sum())


def distance_to(points: np.ndarray, v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """(N,) distance of each point to the triangles ``v[f]``, by brute force over all of them."""
    tri = np.asarray(v, float)[np.asarray(f)]
    near = trimesh.triangles.closest_point(np.tile(tri, (len(points), 1, 1)), np.repeat(points, len(tri), axis=0))
    return np.linalg.norm(near - np.repeat(points, len(tri), axis=0), axis=1).reshape(len(points), -1).min(axis=1)


def same_surface(v1, f1, v2, f2, tol=1e-6) -> bool:
    """Equal areas, and samples of each on the other (to ``tol`` of its size)."""
    a, b = trimesh.Trimesh(v1, f1, process=False), trimesh.Trimesh(v2, f2, process=False)
    size = float(np.ptp(v1, axis=0).max())
    if abs(a.area - b.area) > 1e-6 * a.area:
        return False
    pa, pb = a.sample(500, seed=0), b.sample(500, seed=1)
    return distance_to(pa, v2, f2).max() < tol * size and distance_to(pb, v1, f1).max() < tol * size


def grid(n: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """A flat n x n grid of unit squares, each split into two triangles (2 n^2 faces)."""
    xs = np.arange(n + 1, dtype=float)
    v = np.array([[x, y, 0.0] for y in xs for x in xs])
    f = []
    for y in range(n):
        for x in range(n):
            a, b, c, d = y * (n + 1) + x, y * (n + 1) + x + 1, (y + 1) * (n + 1) + x + 1, (y + 1) * (n + 1) + x
            f += [[a, b, c], [a, c, d]]
    return v, np.array(f)


def test_two_triangles_make_one_quad_in_their_winding():
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    pairs = interior_pairs(f)
    assert len(pairs) == 1
    quad = quad_corners(f, pairs)[0]
    assert sorted(quad) == [0, 1, 2, 3]
    # Counter-clockwise like the triangles, and the diagonal 0-2 gone: 0 and 2 are not neighbours in it.
    k = list(quad).index(0)
    assert [quad[(k + i) % 4] for i in range(4)] == [0, 1, 2, 3]
    assert len(pair_triangles(v, f)) == 1


def test_a_flat_grid_becomes_all_quads():
    v, f = grid(4)
    pairs = pair_triangles(v, f)
    assert len(pairs) == 16 and len(np.unique(pairs[:, :2])) == 32  # every triangle in exactly one quad
    quads = quad_corners(f, pairs)
    assert same_surface(v, f, v, fan(quads.tolist()))
    assert quad_share(16, 0) == 1.0 and quad_share(0, 5) == 0.0 and quad_share(1, 2) == pytest.approx(1 / 3, 1e-3)


def test_no_quad_over_a_sharp_bend_a_sliver_or_inconsistent_winding():
    bent = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 0, 1]], float)  # folded 90 degrees along 0-2
    f = np.array([[0, 1, 2], [0, 2, 3]])
    assert len(pair_triangles(bent, f)) == 0
    assert len(pair_triangles(bent, f, QuadConfig(max_bend=95.0, min_score=0.0, max_angle=179))) == 1
    sliver = np.array([[0, 0, 0], [10, 0, 0], [10, 0.2, 0], [0, 0.2, 0]], float)  # fine: a thin rectangle ...
    assert len(pair_triangles(sliver, f)) == 1
    kite = np.array([[0, 0, 0], [1, 0, 0], [5, 5, 0], [0, 1, 0]], float)  # ... this one has a 10-degree corner
    assert len(pair_triangles(kite, f)) == 0
    assert len(interior_pairs(np.array([[0, 1, 2], [0, 3, 2]]))) == 0  # both walk 0 -> 2: not one surface


def test_a_curved_mesh_is_quad_dominant_and_covers_the_same_surface():
    sphere = trimesh.creation.icosphere(2)
    pairs = pair_triangles(sphere.vertices, sphere.faces)
    assert len(np.unique(pairs[:, :2])) == 2 * len(pairs)
    share = quad_share(len(pairs), len(sphere.faces) - 2 * len(pairs))
    assert share > 0.6, share
    out = MeshOut(vertices=sphere.vertices, faces=sphere.faces, pairs=pairs)
    v, faces, _, _ = read_obj(out.export("obj"))
    assert sum(len(x) == 4 for x in faces) == len(pairs)
    assert same_surface(sphere.vertices, sphere.faces, v, fan(faces))


def box_shape(extents=(1.0, 2.0, 3.0), center=(5.0, -2.0, 1.0)) -> Shape:
    box = trimesh.creation.box(extents=extents)
    return Shape(vertices=np.asarray(box.vertices) + center, faces=np.asarray(box.faces))


def test_quads_through_the_python_api_obj_and_ply(pipe):
    shape = box_shape()
    tri = pipe.generate(shape, GenerateParams())
    assert tri.quality["quads"] == 0 and tri.quality["quad_share"] == 0.0
    assert all(len(f) == 3 for f in read_obj(tri.export("obj"))[1])

    res = pipe.generate(shape, GenerateParams(topology="quad"))
    assert res.quality["quads"] == 6 and res.quality["quad_share"] == 1.0
    assert any("GLB holds triangles" in n for n in res.info["notes"])
    for v, faces in (read_obj(res.export("obj"))[:2], read_ply(res.export("ply"))):
        assert [len(f) for f in faces] == [4] * 6
        assert same_surface(shape.vertices, shape.faces, v, fan(faces), tol=1e-6)
        # Each quad is one flat side of the box: its corners share one coordinate.
        for f in faces:
            assert np.any(np.ptp(v[f], axis=0) < 1e-6)
    glb = trimesh.load(io.BytesIO(res.export("glb")), file_type="glb", force="mesh", process=False)
    assert len(glb.faces) == 12 and np.allclose(glb.area, 22.0)  # GLB: the same surface in triangles


def test_quads_and_triangles_mixed_keep_every_face(pipe):
    """A pyramid: its square base becomes a quad, its four sides stay triangles."""
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 1.0]])
    f = np.array([[0, 2, 1], [0, 3, 2], [0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
    out = MeshOut(vertices=v, faces=f, pairs=pair_triangles(v, f))
    assert out.counts() == {"quads": 1, "quad_share": 0.2}
    for got_v, faces in (read_obj(out.export("obj"))[:2], read_ply(out.export("ply"))):
        assert sorted(len(x) for x in faces) == [3, 3, 3, 3, 4]
        assert same_surface(v, f, got_v, fan(faces))
    kd = cKDTree(v)
    assert kd.query(read_ply(out.export("ply"))[0])[0].max() < 1e-6  # float32 of these coordinates is exact
