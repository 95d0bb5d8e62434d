"""Chamfer / Hausdorff (EVAL.md protocol) and edge metrics."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from fastmesh.evaluation.metrics import (
    CELL,
    chamfer,
    distance_to_triangles,
    edge_metrics,
    hausdorff,
    nearest_distances,
    normalized_samples,
    surface_distance,
    vertex_metrics,
)
from fastmesh.faces.meshops import edges_from_faces
from fastmesh.shapes.io import sample_triangles
from fastmesh.shapes.shape import ShapeError


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


# --------------------------------------------------------------------------- vertex metrics

CORNERS = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)])
SQUARE = (np.array([[-0.5, -0.5, 0.0], [0.5, -0.5, 0], [0.5, 0.5, 0], [-0.5, 0.5, 0]]),
          np.array([[0, 1, 2], [0, 2, 3]]))


def test_vertex_precision_recall_and_count_in_cells():
    gen = np.array([
        CORNERS[0],  # exact
        CORNERS[7] - [CELL, 0, 0],  # exactly one cell: within 1 (<=)
        CORNERS[3] + [0, 1.5 * CELL, 0],  # within 2, not 1
        [0.0, 0.0, 0.0],  # far from every corner
    ])
    m = vertex_metrics(gen, CORNERS)
    assert (m["precision_1"], m["precision_2"]) == (2 / 4, 3 / 4)
    assert (m["recall_1"], m["recall_2"]) == (2 / 8, 3 / 8)
    assert (m["count_ratio"], m["generated"], m["reference"]) == (0.5, 4, 8)
    assert "on_surface" not in m  # no surface given
    # Two generated vertices on one corner: both precise, the corner recalled once.
    m = vertex_metrics(np.stack([CORNERS[0], CORNERS[0] + 0.5 * CELL]), CORNERS)
    assert (m["precision_1"], m["recall_1"], m["count_ratio"]) == (1.0, 1 / 8, 2 / 8)


def test_vertex_metrics_edge_cases():
    m = vertex_metrics(np.zeros((0, 3)), CORNERS, *SQUARE)
    assert m["precision_1"] == 0 and m["recall_2"] == 0 and m["on_surface"] == 0 and m["count_ratio"] == 0
    with pytest.raises(ValueError, match="reference"):
        vertex_metrics(CORNERS, np.zeros((0, 3)))


def test_on_surface_share_uses_the_distance_to_the_triangles():
    gen = np.array([
        [0.1, 0.2, 1.4 * CELL],  # above the square: 1.4 cells
        [0.1, 0.2, -1.6 * CELL],  # below it: 1.6 cells, off
        [0.5 + CELL, 0.0, CELL],  # beside an edge: sqrt(2) cells, on
        [0.5 + 1.1 * CELL, 0.5 + 1.1 * CELL, 0.0],  # beyond a corner: 1.56 cells, off
    ])
    m = vertex_metrics(gen, CORNERS, *SQUARE)
    assert m["on_surface"] == 0.5


def test_distance_to_triangles_known_cases():
    v, f = SQUARE
    pts = np.array([[0.1, 0.2, 0.3], [0.5 + 0.3, 0.0, 0.4], [0.8, 0.9, 0.0], [-0.5, -0.5, 0.0], [0.0, 0.0, 0.0]])
    want = [0.3, 0.5, np.hypot(0.3, 0.4), 0.0, 0.0]
    assert np.allclose(distance_to_triangles(pts, v, f), want, atol=1e-12)


def test_distance_to_triangles_matches_dense_sampling():
    # Exact distances are never above those to points sampled on the surface, and close to them.
    s = trimesh.creation.icosphere(subdivisions=1)
    v, f = np.asarray(s.vertices), np.asarray(s.faces)
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(200, 3)) * 0.8
    samples, _ = sample_triangles(v, f, 400_000, rng)
    approx, _ = nearest_distances(pts, samples.astype(np.float64))
    exact = distance_to_triangles(pts, v, f, chunk=64)  # small chunks: several rows per step
    assert (exact <= approx + 1e-6).all()
    assert np.abs(exact - approx).max() < 0.02
    # Brute force over every triangle agrees with the pruned search.
    from fastmesh.faces.meshops import point_triangle_distance

    brute = point_triangle_distance(np.repeat(pts, len(f), 0), np.tile(v[f], (len(pts), 1, 1))).reshape(len(pts), -1)
    assert np.allclose(exact, brute.min(1), atol=1e-12)
