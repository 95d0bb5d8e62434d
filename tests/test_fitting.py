"""fit_to_planes: vertices move onto the planes around them, only along the directions they fix."""

import numpy as np
import pytest

from fastmesh.fitting import FitConfig, distinct, fit_radius, fit_samples, fit_to_planes
from fastmesh.shapes.shape import Shape


def _cube_samples(n: int = 60000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Samples of the cube [-0.5, 0.5]^3 with their face normals (signs at random)."""
    rng = np.random.default_rng(seed)
    p = rng.uniform(-0.5, 0.5, (n, 3))
    axis = rng.integers(0, 3, n)
    p[np.arange(n), axis] = np.where(rng.random(n) < 0.5, -0.5, 0.5)
    normals = np.zeros_like(p)
    normals[np.arange(n), axis] = np.where(rng.random(n) < 0.5, -1.0, 1.0)
    return p, normals


def _fit_one(x, points, normals, radius, rel):
    """The slow twin: one vertex at a time, the minimiser written out with a pseudo-inverse."""
    d = np.linalg.norm(points - x, axis=1)
    near = d <= radius
    if near.sum() < 3:
        return x
    w = np.exp(-d[near] ** 2 / (2 * (radius / 2) ** 2))
    n, p = normals[near], points[near]
    quad = (n.T * w) @ n
    resid = (n.T * w) @ ((n * (p - x)).sum(1))
    lam, vec = np.linalg.eigh(quad)
    keep = lam > rel * lam[-1]
    delta = vec[:, keep] @ ((vec[:, keep].T @ resid) / lam[keep])
    return x + delta if np.linalg.norm(delta) <= radius else x


def test_corner_edge_and_face_vertices():
    p, n = _cube_samples()
    x = np.array([[0.49, 0.48, 0.495],  # near a corner: onto it
                  [0.3, 0.49, 0.485],  # near an edge: onto the edge, staying at x = 0.3
                  [0.1, -0.2, 0.497]])  # on a face: across it only
    out = fit_to_planes(x, p, n, radius=0.03)
    assert out[0] == pytest.approx([0.5, 0.5, 0.5], abs=1e-9)
    assert out[1] == pytest.approx([0.3, 0.5, 0.5], abs=1e-9)
    assert out[2] == pytest.approx([0.1, -0.2, 0.5], abs=1e-9)


def test_batched_equals_one_at_a_time():
    p, n = _cube_samples(20000, seed=1)
    rng = np.random.default_rng(2)
    x = p[rng.choice(len(p), 200)] + rng.normal(0, 0.01, (200, 3))
    for radius, rel in ((0.02, 0.01), (0.05, 0.2)):
        twin = np.array([_fit_one(xi, p, n, radius, rel) for xi in x])
        assert np.allclose(fit_to_planes(x, p, n, radius, rel), twin, atol=1e-12)


def test_reach_finds_the_corner_that_ends_a_crease():
    p, n = _cube_samples(60000, seed=3)
    gap = np.linalg.norm(p - [0.5, 0.5, 0.5], axis=1) < 0.06  # no sample within 0.06 of the corner
    p, n = p[~gap], n[~gap]
    x = np.array([[0.45, 0.49, 0.49],  # on the crease near the corner: onto the crease, then the corner
                  [0.0, 0.49, 0.49],  # mid-crease: nothing ends it within reach
                  [0.2, 0.1, 0.495]])  # on a face: fixes one direction, not a crease
    near = fit_to_planes(x, p, n, radius=0.03)
    assert near[0] == pytest.approx([0.45, 0.5, 0.5], abs=1e-9)  # the third plane is out of reach
    out = fit_to_planes(x, p, n, radius=0.03, reach=3.0)
    assert out[0] == pytest.approx([0.5, 0.5, 0.5], abs=1e-9)
    assert np.array_equal(out[1:], near[1:])
    assert out[1] == pytest.approx([0.0, 0.5, 0.5], abs=1e-9)


def test_reach_keeps_a_vertex_on_its_crease():
    """At the corner of a thin plate the farther look sees the plate's other side too: the fitted
    point leaves the crease line (into the plate), and the vertex stays where the first fit put it."""
    rng = np.random.default_rng(0)
    lo, hi = np.array([-0.5, -0.5, 0.46]), np.array([0.5, 0.5, 0.5])  # a plate 0.04 thick
    face = rng.choice(6, 80000, p=np.repeat([0.04, 0.04, 1.0], 2) / 2.16)
    axis, top = face // 2, face % 2 == 1
    p = rng.uniform(lo, hi, (80000, 3))
    p[np.arange(80000), axis] = np.where(top, hi[axis], lo[axis])
    n = np.zeros_like(p)
    n[np.arange(80000), axis] = np.where(top, 1.0, -1.0)
    keep = np.linalg.norm(p - hi, axis=1) > 0.03
    x = np.array([[0.46, 0.5, 0.5]])
    near = fit_to_planes(x, p[keep], n[keep], radius=0.02)
    assert near[0] == pytest.approx([0.46, 0.5, 0.5], abs=1e-6)
    assert np.array_equal(fit_to_planes(x, p[keep], n[keep], radius=0.02, reach=4.0), near)


def test_too_few_samples_or_too_far_stays():
    p, n = _cube_samples(200)
    x = np.array([[0.0, 0.0, 0.0], [0.3, 0.3, 0.47]])  # the centre: no sample near
    out = fit_to_planes(x, p, n, radius=0.01)
    assert np.array_equal(out, x)
    inside = np.array([[0.1, 0.1, 0.4]])  # 0.1 below the top face
    assert fit_to_planes(inside, *_cube_samples(), radius=0.11)[0] == pytest.approx([0.1, 0.1, 0.5])
    assert np.array_equal(fit_to_planes(inside, *_cube_samples(), radius=0.05), inside)  # out of reach


def test_samples_of_a_cloud_are_its_points_and_radius_in_cells():
    pts, nrm = _cube_samples(500)
    cloud = Shape(vertices=pts * 2, normals=nrm)
    p, n = fit_samples(cloud, pts, FitConfig(), seed=0)
    assert np.array_equal(p, pts) and np.array_equal(n, nrm)
    mesh = Shape(vertices=np.eye(3), faces=np.array([[0, 1, 2]]))
    p, n = fit_samples(mesh, np.eye(3), FitConfig(points=64), seed=0)
    assert p.shape == (64, 3) and n.shape == (64, 3)
    dense, _ = _cube_samples(60000)
    assert fit_radius(FitConfig(radius=2.0, spacings=2.5), dense) == pytest.approx(2 / 128)  # cells of the unit cube
    sparse, _ = _cube_samples(500)
    spacing = np.median(np.sort(np.linalg.norm(sparse[:, None] - sparse[None], axis=2), axis=1)[:, 1])
    assert spacing * 2.5 > 2 / 128
    assert fit_radius(FitConfig(radius=2.0, spacings=2.5), sparse) == pytest.approx(2.5 * spacing)
    assert fit_radius(FitConfig(radius=None), dense) is None


def test_distinct_keeps_the_first_of_each_cluster():
    rng = np.random.default_rng(4)
    x = rng.uniform(0, 1, (300, 3))
    x[100:150] = x[rng.integers(0, 100, 50)] + rng.normal(0, 1e-4, (50, 3))  # copies of earlier vertices
    x[[7, 8, 9]] = [[0.5, 0.5, 0.5], [0.5, 0.5, 0.5008], [0.5, 0.5, 0.5016]]  # a chain: 9 is 0.0016 from 7
    tol = 1e-3
    twin = []  # the slow twin: each vertex against every kept one
    for i, xi in enumerate(x):
        if all(np.linalg.norm(x[j] - xi) > tol for j in twin):
            twin.append(i)
    keep = distinct(x, tol)
    assert keep.tolist() == twin
    assert 8 not in keep and 9 in keep and not set(range(100, 150)) & set(keep)
    assert distinct(x[:3], tol).tolist() == [0, 1, 2]
