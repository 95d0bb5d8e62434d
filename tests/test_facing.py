"""Open pieces face the input (fastmesh.faces.orient.face_input, the pipeline's last turn): a sheet, a roof or a
terrain has no inside for a signed volume to find, so its side is the input's normals' (turned out of what they
enclose: a Quake model's inward normals too).  Random sheets at random poses and units."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from fastmesh.faces.defects import winding
from fastmesh.faces.orient import face_input
from fastmesh.params import GenerateParams
from fastmesh.pipeline import Pipeline
from fastmesh.shapes.shape import Shape


def _sheet(rng: np.random.Generator, n: int = 60) -> trimesh.Trimesh:
    """A wavy rectangle of random proportions and waves, wound to face +z, turned at random and scaled from
    millimetres to kilometres."""
    x, y = np.meshgrid(np.linspace(-1, 1, n), np.linspace(-1, 1, n) * rng.uniform(0.5, 1.0))
    a, b, c = rng.uniform(0.1, 0.3), rng.uniform(1, 3), rng.uniform(1, 3)
    v = np.c_[x.ravel(), y.ravel(), (a * np.sin(b * x) * np.cos(c * y)).ravel()]
    i = np.arange(n * n).reshape(n, n)
    f = np.r_[np.c_[i[:-1, :-1].ravel(), i[1:, :-1].ravel(), i[:-1, 1:].ravel()],
              np.c_[i[1:, :-1].ravel(), i[1:, 1:].ravel(), i[:-1, 1:].ravel()]]
    if _normals(v, f)[:, 2].mean() < 0:
        f = f[:, ::-1]
    turn = Rotation.random(random_state=rng).as_matrix()
    return trimesh.Trimesh(v @ turn.T * 10.0 ** rng.uniform(-3, 3), f, process=False)


def _normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3) unit normals of the faces as they are wound."""
    tri = np.asarray(vertices)[np.asarray(faces)]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _facing_share(vertices, faces, points, normals) -> float:
    """Of the mesh's area, the share whose faces point the way of the nearest input normal."""
    tri = np.asarray(vertices)[np.asarray(faces)]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nearest = cKDTree(points).query(tri.mean(1))[1]
    with_it = np.einsum("fd,fd->f", n, normals[nearest]) > 0
    area = np.linalg.norm(n, axis=1)
    return float(area[with_it].sum() / area.sum())


def test_face_input_turns_an_open_piece_and_leaves_a_closed_one():
    rng = np.random.default_rng(0)
    sheet = _sheet(rng, n=12)
    box = trimesh.creation.box([1.0, 1.0, 1.0])
    box.apply_translation(sheet.bounds[1] + 1.0)
    points = np.r_[sheet.triangles_center, box.triangles_center]
    normals = np.r_[_normals(sheet.vertices, sheet.faces), _normals(box.vertices, box.faces)]
    v = np.r_[sheet.vertices, box.vertices]
    f = np.r_[np.asarray(sheet.faces)[:, ::-1], np.asarray(box.faces)[:, ::-1] + len(sheet.vertices)]  # both inside out
    out = face_input(v, f, points, normals)
    assert np.array_equal(out[: len(sheet.faces)], sheet.faces)  # the sheet faces its normals again
    assert np.array_equal(out[len(sheet.faces):], f[len(sheet.faces):])  # a closed piece is its own to tell


@pytest.fixture(scope="module")
def shipped() -> Pipeline:
    return Pipeline.from_pretrained(device="cpu", threads=1)


@pytest.mark.parametrize("seed", range(4))
def test_a_generated_sheet_faces_its_input_one_way(shipped, seed):
    """A sheet's result is wound one way and faces the input's normals (before: whole sheets came back facing
    away from them, wound one way but inside out to a renderer)."""
    rng = np.random.default_rng(seed)
    m = _sheet(rng)
    points, index = trimesh.sample.sample_surface(m, 8192, seed=seed)
    normals = _normals(m.vertices, m.faces)[index]
    result = shipped.generate(Shape(vertices=np.asarray(points), normals=np.asarray(normals)), GenerateParams(seed=0))
    assert not result.quality["watertight"]  # an open input's result stays open
    assert winding(result.vertices, result.faces)["misoriented_edges"] == 0
    assert _facing_share(result.vertices, result.faces, np.asarray(points), np.asarray(normals)) > 0.9


def test_an_open_piece_that_encloses_volume_keeps_its_signed_volume_side():
    """A bowl (an open hemisphere) wound outward, its input normals pointing in (a Quake model's): the signed volume
    reads its side, and the normals do not turn it."""
    sphere = trimesh.creation.icosphere(subdivisions=3)
    keep = sphere.triangles_center[:, 2] > -0.2
    bowl = trimesh.Trimesh(sphere.vertices, sphere.faces[keep], process=False)
    inward = -_normals(bowl.vertices, bowl.faces)
    out = face_input(bowl.vertices, bowl.faces, bowl.triangles_center, inward)
    assert np.array_equal(out, bowl.faces)
