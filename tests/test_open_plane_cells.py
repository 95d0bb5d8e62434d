"""Flat props open at the bottom (a building without its floor, a crate without its base) rebuilt from the cells of
their planes (``plane_cells(open_=True)`` through the pipeline's open path): the families of
tests/test_plane_cells.py without their bottom face, any pose, millimetres to kilometres, as oriented points and
as dense meshes; each comes back open only along its bottom outline, wound one way and facing out, on the true
surface both ways (exact distances) with at most ``FACES`` times the truth's own faces.  The outline lies where the
samples stop, which is above the true one by up to the samples' spacing: within ``RIM`` of the size."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from test_plane_cells import FAMILIES, SCALES

from fastmesh.faces.defects import winding
from fastmesh.faces.meshops import (
    distance_to_triangles,
    edge_face_counts,
    face_sides,
    open_sides,
    point_triangle_distance,
)
from fastmesh.params import GenerateParams
from fastmesh.pipeline import Pipeline
from fastmesh.shapes.io import sample_surface
from fastmesh.shapes.shape import Shape

RIM = 2e-3
FACES = 1.5  # a chamfer's outline beside the rim may keep its fan: at most this many times the truth's faces
OPEN_FAMILIES = ("inset", "step", "notch", "bevel")  # a bay's recess reaches the bottom on some draws


def _floorless(solid, rng: np.random.Generator, scale: float) -> tuple[Shape, np.ndarray]:
    """The solid without its faces on its bottom plane, turned at random, scaled by ``scale`` and moved up to 10
    of its sizes from the origin; and (4,) its bottom plane (unit normal n pointing down, n . x = d), posed."""
    mesh = solid.to_mesh()
    v, f = np.asarray(mesh.vert_properties)[:, :3].astype(np.float64), np.asarray(mesh.tri_verts)
    bottom = (np.abs(v[f, 2]) < 1e-9).all(axis=1)
    f = f[~bottom]
    pose = trimesh.transformations.random_rotation_matrix(rng.random(3))
    turn = pose[:3, :3]
    shift = rng.uniform(-10, 10, 3) * scale
    posed = v @ turn.T * scale + shift
    down = turn @ np.array([0.0, 0.0, -1.0])
    return Shape(vertices=posed, faces=f), np.r_[down, down @ shift]


def _input(truth: Shape, rng: np.random.Generator, dense: bool) -> Shape:
    """The truth as a dense mesh (faces of 2 % of its size) or as 8,192 points with their faces' normals."""
    size = float(np.ptp(truth.vertices, axis=0).max())
    if dense:
        tm = trimesh.Trimesh(truth.vertices, truth.faces, process=False).subdivide_to_size(0.02 * size)
        return Shape(vertices=np.asarray(tm.vertices), faces=np.asarray(tm.faces))
    points, normals = sample_surface(truth, 8192, seed=int(rng.integers(1 << 30)))
    return Shape(vertices=points.astype(np.float64), normals=normals.astype(np.float64))


@pytest.fixture(scope="module")
def pipe() -> Pipeline:
    return Pipeline.random("tiny", seed=0)  # the planes path runs before any network


@pytest.mark.parametrize("family", OPEN_FAMILIES)
@pytest.mark.parametrize("dense", [False, True])
def test_floorless_flat_props_come_back_open_at_the_bottom_only(pipe, family, dense):
    rng = np.random.default_rng(OPEN_FAMILIES.index(family) * 2 + dense + 100)
    for scale in SCALES:
        truth, floor = _floorless(FAMILIES[family](rng), rng, scale)
        size = float(np.ptp(truth.vertices, axis=0).max())
        res = pipe.generate(_input(truth, rng, dense), GenerateParams(seed=0))
        # A dense mesh of flat faces may be simplified within its own surface first (``result.flat_faced``).
        assert res.info["result_from"] in (("planes", "simplified") if dense else ("planes",)), (family, scale)
        assert res.tokens == 0
        v, f = res.vertices, res.faces
        assert len(f) <= FACES * len(truth.faces)
        counts = edge_face_counts(f)
        assert counts.max() == 2 and (counts == 1).any()
        rim = np.unique(face_sides(f)[open_sides(f)])
        assert np.abs(v[rim] @ floor[:3] - floor[3]).max() < RIM * size  # open along the bottom outline only
        assert winding(v, f)["misoriented_edges"] == 0
        rng_s = np.random.default_rng(0)
        for (va, fa), (vb, fb) in (((v, f), (truth.vertices, truth.faces)), ((truth.vertices, truth.faces), (v, f))):
            samples = trimesh.Trimesh(va, fa, process=False).sample(4000, seed=rng_s)
            assert distance_to_triangles(samples, vb, fb).max() < RIM * size
        # Facing out: the faces turned the way of the truth's face each lies on.
        tri = v[f]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        t = truth.vertices[truth.faces]
        tn = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        centre = tri.mean(1)
        gap = point_triangle_distance(np.repeat(centre, len(t), axis=0), np.tile(t, (len(centre), 1, 1)))
        nearest = gap.reshape(len(centre), len(t)).argmin(axis=1)
        area = np.linalg.norm(n, axis=1)
        cos = np.einsum("fd,fd->f", n, tn[nearest]) / (area * np.linalg.norm(tn[nearest], axis=1))
        # By area, as a renderer shows it: corners merged within the plane tolerance may leave slivers of no size.
        assert area[cos < 0].sum() < 1e-3 * area.sum()
