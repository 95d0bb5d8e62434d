"""A result's box brought to its input's (``faces.extent``): on a family of random ellipsoids (proportions, poses,
units, places), coarse meshes that fall short of the input's box come to span it, closed, wound alike and turned
the same way; a stray point, a part the mesh lacks and a held face count are left alone."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from fastmesh.evaluation.metrics import box_gap
from fastmesh.evaluation.primitives import point_cloud
from fastmesh.faces.extent import MAX_ADDED, REACH, SHORT, reach_extent
from fastmesh.faces.meshops import edge_face_counts, face_sides
from fastmesh.params import GenerateParams
from fastmesh.pipeline import Pipeline
from fastmesh.shapes.shape import Shape


def _ellipsoid(rng: np.random.Generator, subdivisions: int) -> tuple[np.ndarray, np.ndarray, tuple]:
    """An ellipsoid of random radii (up to 5:1), turned at random, 1 mm to 1 km across, far from the origin: the
    icosphere of ``subdivisions`` mapped onto it; and the pose to make another of the same."""
    radii = rng.uniform(0.2, 1.0, 3)
    turn = trimesh.transformations.random_rotation_matrix(rng.random(3))[:3, :3]
    scale = 10.0 ** rng.uniform(-3, 3)
    shift = rng.uniform(-50, 50, 3) * scale
    return (*_placed(subdivisions, radii, turn, scale, shift), (radii, turn, scale, shift))


def _placed(subdivisions: int, radii, turn, scale, shift) -> tuple[np.ndarray, np.ndarray]:
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    return (np.asarray(sphere.vertices) * radii) @ turn.T * scale + shift, np.asarray(sphere.faces)


def _case(seed: int, size: float, subdivisions: int = 2, points: int = 8192
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``points`` samples of a random ellipsoid (:func:`_ellipsoid`) and a coarser mesh of it ``size`` times as
    big."""
    dense, dense_f, (radii, turn, scale, shift) = _ellipsoid(np.random.default_rng(seed), 4)
    pts = point_cloud(Shape(vertices=dense, faces=dense_f), points, seed=seed).vertices
    return (pts, *_placed(subdivisions, radii * size, turn, scale, shift))


def _volume(v: np.ndarray, f: np.ndarray) -> float:
    c = v.mean(axis=0)
    a, b, d = v[f[:, 0]] - c, v[f[:, 1]] - c, v[f[:, 2]] - c
    return float(np.einsum("ij,ij->i", a, np.cross(b, d)).sum())


def _a_surface(v: np.ndarray, f: np.ndarray) -> bool:
    """Closed, every edge in two faces, run once either way."""
    sides = face_sides(f)
    return bool((edge_face_counts(f) == 2).all() and len(np.unique(sides, axis=0)) == len(sides))


@pytest.mark.parametrize("seed", range(8))
def test_a_coarse_mesh_comes_to_span_the_inputs_box(seed):
    pts, v, f = _case(seed, 0.99)  # 320 faces, a shade small: short on every side
    assert box_gap(v, pts) > 2 * 100 * SHORT
    out_v, out_f, reached = reach_extent(v, f, pts)

    assert reached >= 1
    assert box_gap(out_v, pts) <= 100 * SHORT + 1e-9
    assert _a_surface(out_v, out_f) and np.sign(_volume(out_v, out_f)) == np.sign(_volume(v, f))
    assert len(out_v) <= len(v) + MAX_ADDED and len(out_f) <= len(f) + 2 * MAX_ADDED
    # A vertex is the mesh's own, where it was, or one of the input's points.
    kept = (out_v[:len(v)] == v).all(axis=1)
    on_points = (np.abs(out_v[:, None] - pts[None]).max(axis=-1) == 0).any(axis=1)
    assert (kept | on_points[:len(v)]).all() and on_points[len(v):].all()


def test_vertices_beyond_the_box_come_back_onto_it():
    pts, v, f = _case(11, 1.05)
    out_v, out_f, _ = reach_extent(v, f, pts, add=False)
    assert np.array_equal(out_f, f)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    assert (out_v >= lo).all() and (out_v <= hi).all() and box_gap(out_v, pts) <= 100 * SHORT + 1e-9


def test_a_stray_point_is_no_tip():
    """A stray sample 4 median spacings beyond the surface's outermost point on +x, within ``REACH`` of the
    mesh: the side reaches the surface's point, not the stray."""
    pts, v, f = _case(3, 0.99, points=32768)
    length = np.ptp(pts, axis=0).max()
    spacing = np.median(cKDTree(pts).query(pts, k=2)[0][:, 1])
    stray = pts[np.argmax(pts[:, 0])] + np.array([4 * spacing, 0.0, 0.0])
    assert np.linalg.norm(stray - np.clip(stray, v.min(axis=0), v.max(axis=0))) < REACH * length
    out_v, _, reached = reach_extent(v, f, np.concatenate([pts, stray[None]]))
    assert reached >= 1 and abs(out_v[:, 0].max() - pts[:, 0].max()) <= SHORT * length


def test_a_part_the_mesh_lacks_gets_no_spike():
    """A sphere's points with a long thin arm along +x, the mesh only the sphere: the arm's tip lies beyond
    ``REACH`` of the mesh, so no vertex goes there."""
    sphere = trimesh.creation.icosphere(subdivisions=4)
    arm = trimesh.creation.cylinder(radius=0.08, height=1.0, sections=16)
    arm.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    arm.apply_translation([1.4, 0.0, 0.0])
    both = trimesh.util.concatenate([sphere, arm])
    pts = point_cloud(Shape(vertices=np.asarray(both.vertices), faces=np.asarray(both.faces)), 8192, seed=0).vertices
    coarse = trimesh.creation.icosphere(subdivisions=2)
    v, f = np.asarray(coarse.vertices), np.asarray(coarse.faces)
    out_v, out_f, _ = reach_extent(v, f, pts)
    assert out_v[:, 0].max() <= 1.0 + 1e-9 and len(out_v) <= len(v) + MAX_ADDED
    assert _a_surface(out_v, out_f)


def test_nothing_is_added_where_the_count_is_held_and_a_spanning_mesh_stays_as_it_is():
    pts, v, f = _case(5, 0.99)
    out_v, out_f, _ = reach_extent(v, f, pts, add=False)
    assert len(out_v) == len(v) and np.array_equal(out_f, f)
    box = trimesh.creation.box(extents=(3.0, 1.0, 0.2))
    bv, bf = np.asarray(box.vertices), np.asarray(box.faces)
    same_v, same_f, reached = reach_extent(bv, bf, bv, supported=False)
    assert reached == 0 and np.array_equal(same_v, bv) and np.array_equal(same_f, bf)


@pytest.fixture(scope="module")
def shipped():
    return Pipeline.from_pretrained()


@pytest.mark.parametrize("seed", range(2))
def test_the_pipelines_results_span_their_inputs_box(shipped, seed):
    """Point clouds of random ellipsoids through the shipped pipeline: the result's box is the input's (the
    quality report's ``box_gap``), and the step is the one that made it so."""
    rng = np.random.default_rng(100 + seed)
    dense, dense_f, _ = _ellipsoid(rng, 4)
    cloud = point_cloud(Shape(vertices=dense, faces=dense_f), 8192, seed=seed)
    res = shipped.generate(cloud, GenerateParams(seed=seed, candidates=1))
    assert res.quality["box_gap"] <= 100 * SHORT + 1e-3
    assert res.quality["box_gap"] == pytest.approx(box_gap(res.vertices, cloud.vertices), abs=1e-3)
    assert "extent_sides" in res.info


def test_a_fin_beyond_the_box_is_not_flattened_onto_it():
    """A thin fin standing out of a cube's top, its faces upright: clamping its tip onto the box's top would
    turn its faces over, so it keeps its tip; the rest comes onto the box."""
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    v, f = np.asarray(box.vertices, dtype=np.float64), np.asarray(box.faces)
    tip = np.array([[0.0, 0.0, 0.8]])  # above the top (z = 0.5); the points stop at 0.5
    fin_v = np.concatenate([v, tip])
    top = int(np.flatnonzero((v[:, 2] > 0.4) & (v[:, 0] > 0.4) & (v[:, 1] > 0.4))[0])
    other = int(np.flatnonzero((v[:, 2] > 0.4) & (v[:, 0] < -0.4) & (v[:, 1] < -0.4))[0])
    fin_f = np.concatenate([f, [[top, other, len(v)], [other, top, len(v)]]])
    out_v, out_f, _ = reach_extent(fin_v, fin_f, v, supported=False, add=False)
    assert np.array_equal(out_v[len(v)], tip[0]) and np.array_equal(out_v[:len(v)], v)
    wide = v * 1.1  # every vertex beyond the box: all come onto it, no face turns
    out_v, _, _ = reach_extent(wide, f, v, supported=False, add=False)
    assert np.allclose(out_v, v)
