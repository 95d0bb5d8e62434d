"""The canonical frame (fastmesh.shapes.canonical) on shapes drawn at random: boxes, prisms and point clouds of them."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from fastmesh.evaluation.primitives import point_cloud
from fastmesh.shapes import canonical
from fastmesh.shapes.canonical import (
    aligned_share,
    aligned_share_bound,
    canonical_rotation,
    rotate_shape,
    turned_degrees,
)
from fastmesh.shapes.shape import Shape


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


def _clustered_normals(rng: np.random.Generator) -> np.ndarray:
    """(M, 3) unit normals: clusters of random spread about random directions, and some scattered."""
    centres = rng.normal(size=(int(rng.integers(1, 7)), 3))
    spread = rng.uniform(0.0, 0.2, len(centres))
    n = np.concatenate([c + rng.normal(scale=s, size=(int(rng.integers(5, 300)), 3))
                        for c, s in zip(centres / np.linalg.norm(centres, axis=1, keepdims=True), spread, strict=True)]
                       + [rng.normal(size=(int(rng.integers(0, 200)), 3))])
    return n / np.linalg.norm(n, axis=1, keepdims=True) * rng.uniform(0.5, 2.0, (len(n), 1))


def test_the_aligned_share_bound_holds_for_every_rotation():
    """Random rotations, and the ones that put a cluster's normals, or two of them, on the axes exactly."""
    rng = np.random.default_rng(3)
    for _ in range(60):
        n = _clustered_normals(rng)
        bound = aligned_share_bound(n)
        turns = [trimesh.transformations.random_rotation_matrix(rng.random(3))[:3, :3] for _ in range(20)]
        for i, j in rng.integers(0, len(n), (20, 2)):
            a = n[i] / np.linalg.norm(n[i])
            b = n[j] - (n[j] @ a) * a
            b = b / np.linalg.norm(b) if np.linalg.norm(b) > 1e-9 else np.cross(a, [0.6, 0.0, 0.8])
            b /= np.linalg.norm(b)
            turns.append(np.stack([a, b, np.cross(a, b)]))  # n[i] onto x, n[j] into the xy plane
        assert all(aligned_share(n @ r.T) <= bound for r in turns)


@pytest.mark.parametrize("seed", range(4))
def test_the_bound_leaves_every_frame_as_the_box_search_finds_it(monkeypatch, seed):
    """canonical_rotation against its slow twin, the box searched for every shape: the same rotation on
    smooth shapes (where the bound spares the search), turned boxes and noisy boxes."""
    rng = np.random.default_rng(seed)
    ellipsoid = trimesh.creation.icosphere(3)
    ellipsoid.apply_scale(rng.uniform(0.3, 1.0, 3))
    shapes = [_random_box(rng)[0], trimesh.creation.icosphere(3), ellipsoid, trimesh.creation.torus(1.0, 0.3),
              trimesh.creation.cylinder(0.3, 1.0, sections=48)]
    clouds = []
    for m in shapes:
        m.apply_transform(trimesh.transformations.random_rotation_matrix(rng.random(3)))
        cloud = point_cloud(Shape(vertices=np.asarray(m.vertices), faces=np.asarray(m.faces)), 3000, seed=seed)
        clouds.append((cloud.vertices + rng.normal(scale=0.002, size=cloud.vertices.shape), cloud.normals))
    fast = [canonical_rotation(p, n) for p, n in clouds]
    monkeypatch.setattr(canonical, "aligned_share_bound", lambda normals: 1.0)
    slow = [canonical_rotation(p, n) for p, n in clouds]
    assert all(np.array_equal(a, b) for a, b in zip(fast, slow, strict=True))
    assert sum(aligned_share_bound(n) < aligned_share(n) + canonical.TURN_GAIN for _, n in clouds) >= 2
