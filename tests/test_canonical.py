"""The canonical frame (fastmesh.canonical) on shapes drawn at random: boxes, prisms and point clouds of them."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from fastmesh.canonical import canonical_rotation, rotate_shape, turned_degrees
from fastmesh.io import Shape
from fastmesh.primitives import point_cloud


def _random_box(rng: np.random.Generator) -> tuple[trimesh.Trimesh, np.ndarray]:
    """A box of random proportions turned at random, and its extents."""
    extents = rng.uniform(0.1, 1.0, 3) * 10 ** rng.uniform(-3, 3)
    m = trimesh.creation.box(extents=extents)
    m.apply_transform(trimesh.transformations.random_rotation_matrix(rng.random(3)))
    m.apply_translation(rng.uniform(-1e3, 1e3, 3))
    return m, extents


def _axis_aligned(points: np.ndarray, rot: np.ndarray, extents: np.ndarray, tol: float) -> bool:
    """Whether ``points`` turned by ``rot`` fill an axis-aligned box of ``extents`` (in some order)."""
    turned = points @ rot.T
    return bool(np.allclose(np.sort(np.ptp(turned, axis=0)), np.sort(extents), rtol=tol, atol=0))


def test_turned_boxes_are_laid_along_the_axes():
    rng = np.random.default_rng(0)
    for _ in range(40):
        m, extents = _random_box(rng)
        rot = canonical_rotation(m.vertices)
        assert np.allclose(rot @ rot.T, np.eye(3)) and np.isclose(np.linalg.det(rot), 1.0)
        assert _axis_aligned(np.asarray(m.vertices), rot, extents, 1e-6)


def test_noisy_point_clouds_of_turned_boxes_are_laid_exactly_with_their_normals():
    """A scan's noise tilts the box of its hull by about a degree; the normals of the walls set the frame."""
    rng = np.random.default_rng(1)
    for _ in range(12):
        m, _ = _random_box(rng)
        exact = canonical_rotation(m.vertices)
        cloud = point_cloud(Shape(vertices=np.asarray(m.vertices), faces=np.asarray(m.faces)), 4000,
                            seed=int(rng.integers(100)))
        noisy = cloud.vertices + rng.normal(scale=0.003 * np.ptp(cloud.vertices, axis=0).max(),
                                            size=cloud.vertices.shape)
        assert turned_degrees(canonical_rotation(noisy, cloud.normals) @ exact.T) < 0.01


def test_shapes_already_along_the_axes_are_left_alone():
    rng = np.random.default_rng(2)
    for _ in range(10):
        m = trimesh.creation.box(extents=rng.uniform(0.1, 1.0, 3))
        assert np.array_equal(canonical_rotation(m.vertices), np.eye(3))
    # An irregular blob: its oriented box holds it scarcely tighter than its own axes.
    blob = trimesh.creation.icosphere(2)
    assert np.array_equal(canonical_rotation(blob.vertices * [1.0, 0.8, 0.6]), np.eye(3))


@pytest.mark.parametrize("degrees", [3.0, 10.0, 30.0])
def test_a_small_turn_is_undone_by_the_nearest_labeling(degrees):
    """Of the box's 24 labelings the one nearest the input's axes: a turn of a few degrees comes back as
    exactly that turn, so the input's up stays up."""
    rng = np.random.default_rng(int(degrees))
    m = trimesh.creation.box(extents=rng.uniform(0.2, 1.0, 3))
    turn = trimesh.transformations.rotation_matrix(np.radians(degrees), rng.normal(size=3))
    m.apply_transform(turn)
    rot = canonical_rotation(m.vertices)
    assert abs(turned_degrees(rot) - degrees) < 1e-6
    assert np.allclose(rot @ turn[:3, :3], np.eye(3), atol=1e-9)


def test_flat_and_tiny_inputs():
    tri = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    assert np.array_equal(canonical_rotation(tri), np.eye(3))  # fewer than four points
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=np.float64)
    turn = trimesh.transformations.rotation_matrix(0.7, [1.0, 2.0, 0.5])[:3, :3]
    rot = canonical_rotation(square @ turn.T)  # a turned plane: no volume, still laid flat
    flat = (square @ turn.T) @ rot.T
    assert np.ptp(flat, axis=0).min() < 1e-9


def test_rotate_shape_turns_points_and_normals_together():
    rng = np.random.default_rng(4)
    m, _ = _random_box(rng)
    cloud = point_cloud(Shape(vertices=np.asarray(m.vertices), faces=np.asarray(m.faces)), 500)
    rot = canonical_rotation(cloud.vertices, cloud.normals)
    turned = rotate_shape(cloud, rot)
    assert np.allclose(turned.vertices, cloud.vertices @ rot.T)
    # The normals still stand on the walls: along an axis after the turn.
    assert np.allclose(np.abs(turned.normals).max(1), 1.0, atol=1e-6)
    back = rotate_shape(turned, rot.T)
    assert np.allclose(back.vertices, cloud.vertices) and np.allclose(back.normals, cloud.normals)
