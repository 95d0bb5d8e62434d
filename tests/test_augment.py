"""Perturbed vertex sets of the face task: what each perturbation does to the vertices and the faces."""

from __future__ import annotations

import numpy as np
import trimesh

from fastmesh.faces.meshops import edges_from_faces
from fastmesh.tokenizer import dequantize, quantize_mesh
from fastmesh.tokenizer.grid import CELL
from fastmesh.training.augment import AugmentConfig, perturb_vertex_set


def _sphere():
    m = trimesh.creation.icosphere(subdivisions=2, radius=0.45)
    return quantize_mesh(m.vertices, m.faces)[:2]


def _closed(q, f) -> bool:
    return trimesh.Trimesh(dequantize(q), f, process=False).is_watertight


def _cells(q) -> set:
    return set(map(tuple, q.tolist()))


def test_no_rates_give_the_artist_vertices():
    q, f = _sphere()
    q2, f2 = perturb_vertex_set(q, f, AugmentConfig(), np.random.default_rng(0))
    np.testing.assert_array_equal(q2, q)
    np.testing.assert_array_equal(f2, f)


def test_dropped_vertices_collapse_into_neighbours():
    q, f = _sphere()
    q2, f2 = perturb_vertex_set(q, f, AugmentConfig(vertex_drop=0.05), np.random.default_rng(1))
    assert len(q) - 20 < len(q2) < len(q)
    assert _cells(q2) < _cells(q)
    assert f2.max() < len(q2) and len(edges_from_faces(f2)) < len(edges_from_faces(f))
    assert _closed(q2, f2)  # a collapse keeps the surface closed


def test_extra_vertices_split_faces_on_the_surface():
    q, f = _sphere()
    q2, f2 = perturb_vertex_set(q, f, AugmentConfig(vertex_extra=0.05), np.random.default_rng(2))
    new = _cells(q2) - _cells(q)
    assert _cells(q) < _cells(q2) and len(new) >= 3
    assert len(f2) == len(f) + 2 * (len(q2) - len(q))  # each split face becomes three
    tri = dequantize(q)[f]  # (F, 3, 3)
    for p in dequantize(np.array(sorted(new))):
        closest = trimesh.triangles.closest_point(tri, np.repeat(p[None], len(tri), 0))
        dist = np.linalg.norm(closest - p, axis=1).min()
        assert dist <= np.sqrt(3) / 2 * CELL + 1e-9  # rounded to the cell of a point on a face
    assert _closed(q2, f2)


def test_jittered_vertices_move_one_cell():
    q, f = _sphere()
    q2, f2 = perturb_vertex_set(q, f, AugmentConfig(vertex_jitter=0.3), np.random.default_rng(3))
    assert len(q2) == len(q) and len(f2) == len(f)
    moved = _cells(q2) - _cells(q)
    assert len(moved) > 0.15 * len(q)
    d = np.abs(np.array(sorted(moved))[:, None] - q[None]).sum(-1).min(1)
    assert (d == 1).all()
