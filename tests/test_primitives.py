"""The ladder of simple shapes: closed, outward-facing meshes with the expected vertices."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from fastmesh.evaluation.primitives import LADDER, N_POINTS, point_cloud, primitive, prism

# name: (vertices, faces, volume)
EXPECTED = {
    "box": (8, 12, 1.0),
    "l_block": (12, 20, 0.75 * 0.4),
    "holed_box": (16, 32, (1 - 0.16) * 0.4),
    "cylinder": (34, 64, None),
    "cone": (18, 32, None),
    "icosphere1": (42, 80, None),
    "icosphere2": (162, 320, None),
    "torus": (128, 256, None),
}


@pytest.mark.parametrize("name", list(LADDER))
def test_every_primitive_is_closed_and_faces_outwards(name):
    shape = primitive(name)
    n_v, n_f, volume = EXPECTED[name]
    assert (len(shape.vertices), len(shape.faces)) == (n_v, n_f)
    m = trimesh.Trimesh(shape.vertices, shape.faces, process=False)
    assert m.is_watertight and m.is_winding_consistent
    assert m.volume > 0  # outward normals
    if volume is not None:
        assert m.volume == pytest.approx(volume)
    assert len(np.unique(shape.vertices, axis=0)) == n_v  # no duplicated vertex


def test_ladder_order_and_names():
    assert list(LADDER) == list(EXPECTED)
    with pytest.raises(ValueError, match="unknown primitive"):
        primitive("teapot")


def test_prism_of_a_triangle():
    s = prism(np.array([[0, 0], [1, 0], [0, 1]]), [[0, 1, 2]], np.array([[0, 1, 2]]), 2.0)
    m = trimesh.Trimesh(s.vertices, s.faces, process=False)
    assert len(s.vertices) == 6 and len(s.faces) == 8
    assert m.is_watertight and m.volume == pytest.approx(1.0)


def test_point_cloud_lies_on_the_primitive_with_its_normals():
    mesh = primitive("l_block")
    cloud = point_cloud(mesh, seed=3)
    assert cloud.faces is None and cloud.vertices.shape == cloud.normals.shape == (N_POINTS, 3)
    m = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    # Every sample lies on a face and carries its outward normal.
    _, dist, tri = trimesh.proximity.closest_point_naive(m, cloud.vertices[:500])
    assert dist.max() < 1e-6
    assert np.allclose((m.face_normals[tri] * cloud.normals[:500]).sum(1), 1.0, atol=1e-5)  # outwards
    assert np.array_equal(point_cloud(mesh, seed=3).vertices, cloud.vertices)


@pytest.mark.parametrize("name", ["box", "l_block", "holed_box"])
def test_shipped_weights_give_the_flat_rungs_back_small_and_closed(name):
    """The ladder's flat rungs (benchmarks/primitives.py measures them all): with the shipped weights and
    default settings each comes back closed, in at most 1.5x its vertices (12 for the box), with a vertex
    within one 7-bit cell of each of its own."""
    from scipy.spatial import cKDTree

    from fastmesh.params import GenerateParams
    from fastmesh.pipeline import Pipeline
    from fastmesh.shapes.shape import Normalization
    from fastmesh.tokenizer.grid import CELL

    mesh = primitive(name)
    res = Pipeline.from_pretrained().generate(point_cloud(mesh), GenerateParams())
    norm = Normalization.fit(mesh.vertices)
    near, _ = cKDTree(norm.apply(res.vertices)).query(norm.apply(mesh.vertices))
    assert len(res.vertices) <= 1.5 * len(mesh.vertices)
    assert (near <= CELL).all(), near / CELL
    assert trimesh.Trimesh(res.vertices, res.faces, process=False).is_watertight


def test_round_kinds_are_closed_curved_meshes_a_unit_across():
    from fastmesh.evaluation.primitives import ROUND_KINDS, random_shape

    rng = np.random.default_rng(2)
    for kind in ROUND_KINDS:
        for _ in range(3):
            s = random_shape(kind, rng)
            m = trimesh.Trimesh(s.vertices, s.faces, process=False)
            assert m.is_watertight and m.is_winding_consistent and m.volume > 0, kind
            assert np.ptp(s.vertices, axis=0).max() == pytest.approx(1.0) and len(s.faces) >= 48, kind


def test_shipped_weights_close_curved_meshes_of_random_proportions():
    """Capsules of random length and radius (``random_shape``), turned at random, given as their dense meshes
    (4,096 thin faces each) and as points: every result is closed and in one piece.  A mesh input's support
    check reads denser samples than a point cloud gives, but its limit stays as wide (``support.SPACING_POINTS``):
    narrowed with their spacing, the coarse faces across the caps fail it."""
    from fastmesh.evaluation.primitives import posed, random_shape
    from fastmesh.params import GenerateParams
    from fastmesh.pipeline import Pipeline

    pipe = Pipeline.from_pretrained()
    rng = np.random.default_rng(11)
    for _ in range(4):
        mesh = posed(random_shape("capsule", rng), rng)
        for shape in (mesh, point_cloud(mesh)):
            q = pipe.generate(shape, GenerateParams()).quality
            assert q["watertight"] and q["components"] == 1, (np.ptp(mesh.vertices, axis=0), shape.faces is None, q)
