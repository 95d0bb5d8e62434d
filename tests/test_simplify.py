"""collapse_flat: the vertices of flat regions, straight creases and straight borders go; the shape stays."""

from dataclasses import replace

import numpy as np
import pytest
import trimesh

from fastmesh.faces import mesh_from_adjacency
from fastmesh.faces.simplify import collapse_flat
from fastmesh.faces.triangles import TriangleConfig


def _kept(faces: np.ndarray) -> int:
    return len(np.unique(faces))


def _grid(n: int) -> tuple[np.ndarray, np.ndarray]:
    """A flat open n x n grid of squares in z = 0, two triangles each, wound towards +z."""
    xs = np.linspace(0.0, 1.0, n + 1)
    v = np.array([(x, y, 0.0) for y in xs for x in xs])
    f = []
    for j in range(n):
        for i in range(n):
            a = j * (n + 1) + i
            f += [(a, a + 1, a + n + 2), (a, a + n + 2, a + n + 1)]
    return v, np.array(f)


def test_subdivided_box_becomes_its_eight_corners():
    m = trimesh.creation.box().subdivide().subdivide()
    f = collapse_flat(m.vertices, m.faces, 1e-3)
    out = trimesh.Trimesh(m.vertices, f)
    out.remove_unreferenced_vertices()
    assert len(out.vertices) == 8 and len(out.faces) == 12
    assert out.is_watertight and out.is_winding_consistent
    assert out.volume == pytest.approx(1.0)  # windings kept: the volume is positive and the box whole
    assert np.allclose(np.abs(out.vertices), 0.5)


def test_cylinder_keeps_its_two_rings():
    m = trimesh.creation.cylinder(radius=0.3, height=1.0, sections=16).subdivide()
    f = collapse_flat(m.vertices, m.faces, 1e-3)
    kept = m.vertices[np.unique(f)]
    assert len(kept) == 32  # the rim vertices: every one turns the surface
    assert np.allclose(np.abs(kept[:, 2]), 0.5)
    assert trimesh.Trimesh(m.vertices, f).is_watertight


def test_curved_surface_is_kept():
    m = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    f = collapse_flat(m.vertices, m.faces, 0.5 / 128)
    assert _kept(f) == len(m.vertices)


def test_collapses_do_not_pile_up_errors():
    """A finer sphere loses vertices, each collapse within tol of the faces as they are then, and the
    result still lies within tol of the sphere: faces stop collapsing once their planes part."""
    m = trimesh.creation.icosphere(subdivisions=4, radius=0.5)
    tol = 0.5 / 128
    f = collapse_flat(m.vertices, m.faces, tol)
    assert 400 < _kept(f) < len(m.vertices)
    out = trimesh.Trimesh(m.vertices, f)
    assert out.is_watertight
    pts, _ = trimesh.sample.sample_surface(out, 20000, seed=0)
    assert np.abs(np.linalg.norm(pts, axis=1) - 0.5).max() <= tol


def test_flat_open_grid_keeps_its_corners():
    v, f = _grid(4)
    out = collapse_flat(v, f, 1e-6)
    assert _kept(out) == 4 and len(out) == 2
    assert set(map(tuple, v[np.unique(out)][:, :2])) == {(0, 0), (1, 0), (0, 1), (1, 1)}
    n = np.cross(v[out[:, 1]] - v[out[:, 0]], v[out[:, 2]] - v[out[:, 0]])
    assert (n[:, 2] > 0).all()  # still facing +z


def test_border_corner_is_kept():
    """An L of squares: the border turns at the inner corner, which must stay."""
    v, f = _grid(4)
    inner = (v[:, 0] > 0.5 + 1e-9) & (v[:, 1] > 0.5 + 1e-9)
    f = f[~inner[f].any(axis=1)]  # cut out the upper right quarter
    out = collapse_flat(v, f, 1e-6)
    kept = {tuple(p) for p in v[np.unique(out)][:, :2]}
    assert (0.5, 0.5) in kept
    assert kept == {(0, 0), (1, 0), (1, 0.5), (0.5, 0.5), (0.5, 1), (0, 1)}


def test_tolerance_separates_noise_from_shape():
    rng = np.random.default_rng(0)
    v, f = _grid(6)
    interior = (v[:, :2] > 1e-9).all(1) & (v[:, :2] < 1 - 1e-9).all(1)
    noisy = v.copy()
    noisy[interior, 2] += rng.uniform(-1e-3, 1e-3, interior.sum())
    assert _kept(collapse_flat(noisy, f, 5e-3)) == 4  # noise below the tolerance: flat
    assert _kept(collapse_flat(noisy, f, 1e-5)) == len(v)  # above it: every bump is shape
    bumped = v.copy()
    bumped[interior, 2] = 0.1 * np.sin(3 * v[interior, 0])
    out = collapse_flat(bumped, f, 5e-3)
    kept = bumped[np.unique(out)]
    assert len(kept) > 4 and np.abs(kept[:, 2]).max() > 0.05  # a curved patch keeps vertices


def test_corners_and_fans_that_are_not_a_disc_stay():
    box = trimesh.creation.box()
    assert _kept(collapse_flat(box.vertices, box.faces, 1e-3)) == 8  # every vertex a corner
    v, f = _grid(2)
    centre = 4  # flat: would go, were it not for the fin that stands on it
    fin = np.vstack([v, [[0.5, 0.5, 1.0], [0.5, 1.0, 1.0]]])
    out = collapse_flat(fin, np.vstack([f, [[centre, 9, 10]]]), 1e-6)
    assert centre in np.unique(out)
    assert _kept(collapse_flat(v, f, 1e-6)) == 4


def test_mesh_from_adjacency_applies_flat_tol():
    """The clean-up's last step; off with flat_tol=None."""
    v, f = _grid(3)
    edges = np.unique(np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [0, 2]]]), axis=1), axis=0)
    rule = TriangleConfig(selection="cliques", drop_coplanar_diagonals=False, support_tol=None, max_faces_per_edge=None)
    on = mesh_from_adjacency(v, edges, rule)
    off = mesh_from_adjacency(v, edges, replace(rule, flat_tol=None))
    assert len(off[0]) == 16 and len(on[0]) == 4
