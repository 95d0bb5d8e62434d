"""Chamfer / Hausdorff (EVAL.md protocol) and edge metrics."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from fastmesh.io import ShapeError, sample_triangles
from fastmesh.metrics import (
    chamfer,
    edge_metrics,
    edges_from_faces,
    hausdorff,
    nearest_distances,
    normalized_samples,
    surface_distance,
)


def _box(extents=(1.0, 1.0, 1.0)):
    b = trimesh.creation.box(extents=extents)
    return np.asarray(b.vertices), np.asarray(b.faces)


def test_identical_meshes_are_close_and_deterministic():
    s = trimesh.creation.icosphere(subdivisions=2)
    a = (s.vertices, s.faces)
    d1 = surface_distance(a, a)
    d2 = surface_distance(a, a)
    assert d1 == d2  # fixed seed
    assert d1.cd == 0.0 and d1.hd == 0.0  # same seed, same mesh: the very same samples


def test_invariant_to_translation_and_scale():
    s = trimesh.creation.icosphere(subdivisions=2)
    b = _box()
    d = surface_distance((s.vertices, s.faces), b)
    moved = surface_distance((s.vertices * 7.5 + [3, -2, 100], s.faces), (b[0] * 0.01 - 4, b[1]))
    assert d.cd == pytest.approx(moved.cd, rel=1e-6)
    assert d.hd == pytest.approx(moved.hd, rel=1e-6)


def test_known_distance_between_parallel_planes():
    # Two unit squares 0.2 apart along z, inside one 1 x 1 x 0.2 box: after the shared normalisation
    # (longest side 1) every point is 0.2 from the other square -> CD = HD = 20 %.
    sq = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=float)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    both_v = np.concatenate([sq, sq + [0, 0, 0.2]])
    both_f = np.concatenate([f, f + 4])
    top_only = (both_v, both_f[2:])  # same bounding box through the unused bottom vertices
    bottom_only = (both_v, both_f[:2])
    d = surface_distance(top_only, bottom_only)
    assert d.cd == pytest.approx(20.0, abs=1e-6)
    assert d.hd == pytest.approx(20.0, abs=1e-6)


def test_formula_matches_brute_force():
    s = trimesh.creation.icosphere(subdivisions=1)
    b = _box((1.0, 0.5, 0.25))
    pa = normalized_samples(s.vertices, s.faces, n=500, seed=3)
    pb = normalized_samples(*b, n=500, seed=3)
    dm = np.linalg.norm(pa[:, None] - pb[None], axis=2)
    cd = 100 * (dm.min(1).mean() + dm.min(0).mean()) / 2
    hd = 100 * max(dm.min(1).max(), dm.min(0).max())
    d = surface_distance((s.vertices, s.faces), b, n=500, seed=3)
    assert d.cd == pytest.approx(cd, rel=1e-9) and d.hd == pytest.approx(hd, rel=1e-9)
    assert chamfer((s.vertices, s.faces), b, n=500, seed=3) == d.cd
    assert hausdorff((s.vertices, s.faces), b, n=500, seed=3) == d.hd
    ab, ba = nearest_distances(pa, pb)
    assert np.allclose(ab, dm.min(1)) and np.allclose(ba, dm.min(0))


def test_samples_are_normalised_and_area_weighted():
    v, f = _box((4.0, 2.0, 1.0))
    p = normalized_samples(v, f, n=5000, seed=0)
    assert p.shape == (5000, 3)
    assert np.allclose(p.max(0) - p.min(0), [1.0, 0.5, 0.25], atol=0.01)
    # Area share of the two 4 x 2 faces (z = +-0.125 after scaling): 16 / 28 of the surface.
    on_z = np.isclose(np.abs(p[:, 2]), 0.125, atol=1e-6).mean()
    assert on_z == pytest.approx(16 / 28, abs=0.03)


def test_point_cloud_input():
    s = trimesh.creation.icosphere(subdivisions=3)
    pts, _ = sample_triangles(np.asarray(s.vertices), np.asarray(s.faces), 3000, np.random.default_rng(1))
    d = surface_distance((s.vertices, s.faces), (pts, None))
    assert d.cd < 3.0


def test_degenerate_mesh_raises():
    v = np.zeros((3, 3))
    with pytest.raises(ShapeError):
        surface_distance((v, np.array([[0, 1, 2]])), _box())


def test_edges_from_faces():
    e = edges_from_faces(np.array([[0, 1, 2], [2, 1, 3]]))
    assert e.tolist() == [[0, 1], [0, 2], [1, 2], [1, 3], [2, 3]]
    assert edges_from_faces(np.zeros((0, 3), dtype=int)).shape == (0, 2)


def test_edge_metrics():
    true = np.array([[0, 1], [1, 2], [0, 2], [2, 3]])
    pred = np.array([[1, 0], [2, 1], [1, 0], [3, 4], [5, 5]])  # duplicates and a self-loop are ignored
    m = edge_metrics(pred, true)
    assert (m["tp"], m["fp"], m["fn"]) == (2, 1, 2)
    assert m["precision"] == pytest.approx(2 / 3) and m["recall"] == pytest.approx(0.5)
    assert m["f1"] == pytest.approx(2 * (2 / 3) * 0.5 / (2 / 3 + 0.5))
    empty = np.zeros((0, 2), dtype=int)
    assert edge_metrics(empty, true)["recall"] == 0 and edge_metrics(empty, true)["f1"] == 0
    assert edge_metrics(empty, empty)["f1"] == 1.0
    assert edge_metrics(true, true)["f1"] == 1.0
