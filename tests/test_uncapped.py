"""An open input's solid loses the faces across the input's openings (fastmesh.faces.uncapped): a floorless box's
floor and an open cup's cap go, at any proportions, pose and unit; a closed input's solid and a face that bridges
a concavity stay; the solid stage reports what it took off."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from poses import posed, random_pose, turned
from scipy.spatial import cKDTree

from fastmesh.faces import solid as sd
from fastmesh.faces.meshops import face_sides, open_sides, triangle_areas, wound_alike
from fastmesh.faces.support import support_limit
from fastmesh.faces.uncapped import across_openings, uncapped


def _sampled(m: trimesh.Trimesh, keep: np.ndarray, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` samples (points, outward normals) of the faces ``keep`` of ``m`` only: the input with an opening."""
    part = m.submesh([np.flatnonzero(keep)], append=True)
    pts, fi = trimesh.sample.sample_surface(part, n, seed=seed)
    return np.asarray(pts), np.asarray(part.face_normals[fi])


def _floorless_box(rng: np.random.Generator):
    """A box of random proportions cut finer (its floor y = min), its samples without the floor, posed at random."""
    m = trimesh.creation.box(rng.uniform(0.3, 1.0, 3)).subdivide().subdivide()
    floor = m.face_normals[:, 1] < -0.99
    pts, nrm = _sampled(m, ~floor, 8192, int(rng.integers(1 << 31)))
    pose = random_pose(rng)
    return posed(m.vertices, pose), np.asarray(m.faces), floor, posed(pts, pose), turned(nrm, pose)


@pytest.mark.parametrize("seed", range(4))
def test_a_floorless_boxs_floor_is_across_its_opening(seed):
    """The floor of a box whose input has none lies across the opening, its sides and top do not: at least
    three quarters of the floor's area is taken off and nothing else, and what stays is wound alike, open in the
    floor only."""
    v, f, floor, pts, nrm = _floorless_box(np.random.default_rng(seed))
    off = across_openings(v, f, pts, nrm, seed)
    assert not off[~floor].any()
    area = triangle_areas(v, f)
    assert area[off].sum() >= 0.75 * area[floor].sum()
    out_v, out_f, taken = uncapped(v, f, pts, nrm, seed)
    assert taken == off.sum() and len(out_f) == len(f) - taken and wound_alike(out_f)
    # The opening is in the floor: every open edge of what stays joins two of the floor's corners.
    kept = f[~off]
    assert np.isin(face_sides(kept)[open_sides(kept)], f[floor]).all() and open_sides(kept).any()


@pytest.mark.parametrize("seed", range(3))
def test_a_closed_inputs_faces_and_a_bridged_concavity_stay(seed):
    """Nothing of a closed box is across an opening; nor are the faces of an L-shaped prism's hull that bridge
    its notch: they lie as far from the input, but outside it (its winding number about 0 there, not a half)."""
    rng = np.random.default_rng(seed)
    m = trimesh.creation.box(rng.uniform(0.3, 1.0, 3)).subdivide()
    pts, nrm = _sampled(m, np.ones(len(m.faces), bool), 8192, seed)
    pose = random_pose(rng)
    v, pts, nrm = posed(m.vertices, pose), posed(pts, pose), turned(nrm, pose)
    assert not across_openings(v, np.asarray(m.faces), pts, nrm, seed).any()
    a, b = trimesh.creation.box((1.0, 0.4, 0.5)), trimesh.creation.box((0.4, 1.0, 0.5))
    a.apply_translation((0.5, 0.2, 0.0))
    b.apply_translation((0.2, 0.5, 0.0))
    ell = trimesh.boolean.union([a, b], engine="manifold")
    hull = ell.convex_hull
    pts, nrm = _sampled(ell, np.ones(len(ell.faces), bool), 8192, seed)
    far = cKDTree(pts).query(hull.triangles_center)[0] > 2 * support_limit(pts, 0.0)
    assert far.any()  # the faces over the notch lie far from the input ...
    assert not across_openings(hull.vertices, hull.faces, pts, nrm, seed).any()  # ... but across no opening


def _open_cup(rng: np.random.Generator):
    """Rings of a cylinder of random proportions and 16-40 sides, and its top's centre; samples of its side and
    top only (the bottom open), posed at random."""
    sides, radius, height = int(rng.integers(16, 41)), rng.uniform(0.3, 0.6), rng.uniform(0.5, 1.2)
    m = trimesh.creation.cylinder(radius, height, sections=sides)
    m = m.subdivide()
    bottom = m.face_normals[:, 2] < -0.99
    pts, nrm = _sampled(m, ~bottom, 8192, int(rng.integers(1 << 31)))
    t = np.linspace(0, 2 * np.pi, sides, endpoint=False)
    rings = [np.c_[radius * np.cos(t), radius * np.sin(t), np.full(sides, z)]
             for z in np.linspace(-height / 2, height / 2, 4)]
    v = np.concatenate([*rings, [[0.0, 0.0, height / 2]]])
    pose = random_pose(rng)
    return posed(v, pose), posed(pts, pose), turned(nrm, pose), pose[1] * np.array([radius, height])


@pytest.mark.parametrize("seed", range(3))
def test_the_solid_of_an_open_cup_stays_open_where_its_input_is(seed):
    """An open input (a cup: a cylinder's side and top, no bottom) gets its solid cut as a closed one's, whose
    bottom caps the opening; with ``open_`` the cap is taken off: the result is open, wound alike, and lies on
    the input (no face farther than a few support limits), while the closed cut keeps faces far inside."""
    v, pts, nrm, (radius, height) = _open_cup(np.random.default_rng(seed))
    rival = (v, np.zeros((0, 3), dtype=np.int64))
    closed = sd.solid_mesh(v, pts, nrm, None, None, rival, pts, 1.1, seed=seed, patch=False)
    opened = sd.solid_mesh(v, pts, nrm, None, None, rival, pts, 1.1, seed=seed, patch=False, open_=True)
    assert closed[2]["faces_from"] == opened[2]["faces_from"] == "solid"
    assert closed[2]["uncapped_faces"] == 0 and opened[2]["uncapped_faces"] > 0
    assert sd.is_closed_surface(closed[1]) and open_sides(opened[1]).any()
    assert wound_alike(opened[1])
    limit = support_limit(pts, 0.0)
    tree = cKDTree(pts)
    far = [tree.query(out_v[out_f].mean(1))[0].max() for out_v, out_f, _ in (closed, opened)]
    assert far[0] > radius / 4 and far[1] < 3 * limit
