"""Faces checked against the input surface (fastmesh.faces.support)."""

import numpy as np
import pytest
import trimesh
from poses import posed, random_pose
from scipy.spatial import cKDTree
from test_visible import _moebius

from fastmesh.faces import mesh_from_adjacency
from fastmesh.faces.crossings import crossing_faces
from fastmesh.faces.meshops import edges_from_faces, triangle_areas
from fastmesh.faces.support import (
    DEFECT_WEIGHT,
    SupportCache,
    defect_share,
    drop_unsupported,
    hole_faces,
    support_distance,
    surface_fit,
    weighed_fit,
)
from fastmesh.faces.triangles import TriangleConfig
from fastmesh.shapes.io import input_surface, sample_triangles
from fastmesh.shapes.shape import Shape

# The paper's rule alone: every 3-clique of the edges, none of the shipped clean-up.
RULE = {"selection": "cliques", "drop_coplanar_diagonals": False, "support_tol": None, "max_faces_per_edge": None,
        "remove_unreferenced": False}


def _grid(n: int, x0: float, x1: float) -> np.ndarray:
    """(n*n, 3) points on the square [x0, x1] x [0, 1] at z = 0."""
    u = np.linspace(0, 1, n)
    xx, yy = np.meshgrid(x0 + (x1 - x0) * u, u)
    return np.stack([xx.ravel(), yy.ravel(), np.zeros(n * n)], 1)


def _two_squares():
    """Two unit squares side by side with a gap of 1 (x in [0,1] and [2,3]); the input samples both."""
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0],
                  [2, 0, 0], [3, 0, 0], [3, 1, 0], [2, 1, 0]], float)
    real = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    bridge = np.array([[1, 4, 7], [1, 7, 2]])  # spans the empty gap between the squares
    points = np.concatenate([_grid(40, 0, 1), _grid(40, 2, 3)])
    return v, real, bridge, points


def test_support_distance_is_zero_on_the_surface_and_large_across_a_gap():
    v, real, bridge, points = _two_squares()
    d = support_distance(v, np.concatenate([real, bridge]), points)
    assert d.shape == (6,)
    assert (d[:4] < 0.02).all()
    assert (d[4:] > 0.2).all()


def test_support_cache_equals_support_distance_with_repeats_and_windings():
    """The cache against its slow twin: faces asked for again (alone, in other batches, within one
    batch, in another winding, which samples the face differently) get exactly what a direct call gives."""
    rng = np.random.default_rng(0)
    v = rng.uniform(0, 3, size=(30, 3))
    points = rng.uniform(0, 3, size=(500, 3))
    cache = SupportCache(v, points)
    faces = rng.integers(0, 30, size=(40, 3))
    for batch in (faces[:10], faces, faces[[3, 3, 7, 3]], faces[:, [1, 2, 0]], faces[:0]):
        assert np.array_equal(cache(batch), support_distance(v, batch, points))
    assert not np.array_equal(support_distance(v, faces[:, [1, 2, 0]], points), support_distance(v, faces, points))


def test_faces_across_empty_space_are_dropped_and_the_others_kept():
    v, real, bridge, points = _two_squares()
    kept = drop_unsupported(v, np.concatenate([real, bridge]), points, tol=0.03)
    assert kept.tolist() == real.tolist()


def test_sparse_samples_do_not_drop_faces_that_lie_on_them():
    """The limit grows with the point spacing: 5 x 5 samples of a square still support its faces."""
    v, real, _, _ = _two_squares()
    sparse = np.concatenate([_grid(5, 0, 1), _grid(5, 2, 3)])
    assert drop_unsupported(v, real, sparse, tol=0.01).tolist() == real.tolist()


def test_a_vertex_on_the_surface_keeps_its_best_face():
    """A thin part whose only faces stray (a spike to a correct tip) is not cut off: the tip keeps one face."""
    v, real, _, points = _two_squares()
    tip = np.array([[0.5, 0.5, 1.0]])  # on the input: a pole sampled along x = y = 0.5
    pole = np.stack([np.full(50, 0.5), np.full(50, 0.5), np.linspace(0, 1, 50)], 1)
    v = np.concatenate([v, tip])
    spikes = np.array([[0, 1, 8], [1, 2, 8], [2, 3, 8]])  # wide fans from the square's corners to the tip
    faces = np.concatenate([real, spikes])
    kept = drop_unsupported(v, faces, np.concatenate([points, pole]), tol=0.03)
    assert 8 in kept  # the tip stays in the mesh
    assert len(kept) == len(real) + 1
    # The same fans to a tip that no input point supports all go.
    v_off = v.copy()
    v_off[8] = [0.5, 0.5, 3.0]
    assert drop_unsupported(v_off, faces, np.concatenate([points, pole]), tol=0.03).tolist() == real.tolist()


def test_mesh_from_adjacency_checks_support_only_when_asked():
    v, real, bridge, points = _two_squares()
    edges = edges_from_faces(np.concatenate([real, bridge]))
    _, f_all = mesh_from_adjacency(v, edges, TriangleConfig(**RULE, orient=False))
    checked = TriangleConfig(**{**RULE, "support_tol": 0.03}, orient=False)
    _, f_sup = mesh_from_adjacency(v, edges, checked, points=points)
    _, f_nopts = mesh_from_adjacency(v, edges, checked)
    assert len(f_all) == len(f_nopts) > len(f_sup)
    # No kept triangle joins the two squares (vertices 0-3 and 4-7).
    assert all(len({int(i) // 4 for i in f}) == 1 for f in f_sup)


def test_support_on_a_sampled_mesh_keeps_every_face():
    sphere = trimesh.creation.icosphere(2)
    points = sample_triangles(sphere.vertices, sphere.faces, 20000, np.random.default_rng(0))[0]
    kept = drop_unsupported(sphere.vertices, sphere.faces, points, tol=0.03)
    assert len(kept) == len(sphere.faces)


def test_input_surface_keeps_a_small_point_cloud_and_samples_the_rest():
    rng = np.random.default_rng(0)
    small, big = rng.normal(size=(300, 3)), rng.normal(size=(5000, 3))
    cloud = Shape(vertices=small, normals=np.tile([0.0, 0.0, 1.0], (300, 1)))
    assert np.array_equal(input_surface(cloud, small * 2, 1000, seed=0), small * 2)  # all, in the given frame
    dense = Shape(vertices=big, normals=np.tile([0.0, 0.0, 1.0], (5000, 1)))
    out = input_surface(dense, big, 1000, seed=0)
    assert len(out) == 1000 and len(np.unique(out, axis=0)) == 1000  # no duplicates
    sphere = trimesh.creation.icosphere(2)
    mesh = Shape(vertices=sphere.vertices, faces=sphere.faces)
    assert input_surface(mesh, sphere.vertices, 1000, seed=0).shape == (1000, 3)


def test_surface_fit_is_small_on_the_surface_and_grows_with_what_is_missing_or_stray():
    sphere = trimesh.creation.icosphere(3)
    points = sample_triangles(sphere.vertices, sphere.faces, 20000, np.random.default_rng(1))[0]
    whole = surface_fit(sphere.vertices, sphere.faces, points)
    half = surface_fit(sphere.vertices, sphere.faces[sphere.triangles_center[:, 2] > 0], points)
    stray = surface_fit(sphere.vertices * 1.3, sphere.faces, points)
    assert whole < 0.03 and half > 5 * whole and stray > 10 * whole  # whole: the sampling noise alone


def test_surface_fit_prefers_a_whole_mesh_to_one_with_a_hole_of_the_same_mean():
    """A sphere with its cap cut off and a sphere 2 % too large are about as far from the input on average
    (the Chamfer part prefers the hole); the share of the worst distance prefers the whole one."""
    sphere = trimesh.creation.icosphere(3)
    points = sample_triangles(sphere.vertices, sphere.faces, 20000, np.random.default_rng(1))[0]
    holed = sphere.faces[sphere.triangles_center[:, 2] < 0.9]
    larger = sphere.vertices * 1.02
    assert surface_fit(sphere.vertices, holed, points, hausdorff_weight=0) < surface_fit(larger, sphere.faces, points,
                                                                                      hausdorff_weight=0)
    assert surface_fit(sphere.vertices, holed, points) > surface_fit(larger, sphere.faces, points)


def test_a_bounded_search_is_exact_within_its_bound_and_above_it_beyond():
    """Faces on the surface and across the gap, with the bound between them and at a face's own distance:
    every distance up to the bound is the unbounded one exactly, every other is above the bound."""
    v, real, bridge, points = _two_squares()
    rng = np.random.default_rng(1)
    faces = np.concatenate([real, bridge, rng.integers(0, len(v), (40, 3))])
    free = support_distance(v, faces, points)
    for bound in (0.05, 0.2, float(np.sort(free)[len(free) // 2])):
        d = support_distance(v, faces, points, bound=bound)
        within = free <= bound
        assert within.any() and (~within).any()
        assert np.array_equal(d[within], free[within])
        assert (d[~within] > bound).all()
        cache = SupportCache(v, points, bound=bound)
        assert np.array_equal(cache(faces) <= bound, within)


def test_the_limit_is_as_wide_on_denser_samples_and_wider_on_sparser_ones():
    """``support_limit``'s floor reads the spacing ``SPACING_POINTS`` samples of the surface would have: 4x or 16x
    as many samples of a random ellipsoid leave it within a few percent, a quarter as many widen it about 2x."""
    from fastmesh.faces.support import SPACING_FACTOR, SPACING_POINTS, support_limit

    rng = np.random.default_rng(4)
    for _ in range(3):
        m = trimesh.creation.icosphere(4)
        m.apply_scale(rng.uniform(0.3, 1.0, 3))
        v, f = np.asarray(m.vertices), np.asarray(m.faces)
        limit = {k: support_limit(sample_triangles(v, f, int(k * SPACING_POINTS), rng)[0], 0.0)
                 for k in (0.25, 1, 4, 16)}
        for k in (4, 16):
            assert abs(limit[k] / limit[1] - 1) < 0.05, limit
        assert 1.8 < limit[0.25] / limit[1] < 2.2, limit
        # The floor is SPACING_FACTOR spacings of the SPACING_POINTS samples themselves.
        pts = sample_triangles(v, f, SPACING_POINTS, rng)[0]
        nn = cKDTree(pts).query(pts, k=2)[0][:, 1]
        assert limit[1] / (SPACING_FACTOR * np.median(nn)) == pytest.approx(1.0, rel=0.05)


@pytest.mark.parametrize("seed", range(3))
def test_a_rival_folded_through_itself_weighs_more_than_its_clean_twin(seed):
    """At any pose and unit a clean sphere weighs its fit alone; the same sphere with a copy turned a little
    through it (nearly every face crossing) lies as near the input yet weighs ~1 + DEFECT_WEIGHT times as much,
    more than a much coarser clean sphere; a Moebius band weighs the share of its faces along its twist."""
    rng = np.random.default_rng(seed)
    rot = trimesh.transformations.random_rotation_matrix(rng.random(3))[:3, :3]
    scale, offset = 10.0 ** rng.uniform(-3, 3), rng.normal(size=3)
    place = lambda v: (np.asarray(v) @ rot.T + offset) * scale  # noqa: E731
    fine, coarse = trimesh.creation.icosphere(3), trimesh.creation.icosphere(1)
    points = place(trimesh.creation.icosphere(5).vertices)
    turned = fine.vertices @ trimesh.transformations.rotation_matrix(0.05, [0, 0, 1])[:3, :3].T
    folded_v = place(np.concatenate([fine.vertices, turned]))
    folded_f = np.concatenate([fine.faces, fine.faces + len(fine.vertices)])
    clean = weighed_fit(place(fine.vertices), fine.faces, points, seed)
    assert clean == surface_fit(place(fine.vertices), fine.faces, points, seed)
    share = defect_share(folded_v, folded_f)  # all but the faces at the turn's axis, whose corners stay put
    assert share > 0.95
    folded = weighed_fit(folded_v, folded_f, points, seed)
    assert folded == pytest.approx((1 + DEFECT_WEIGHT * share) * surface_fit(folded_v, folded_f, points, seed))
    assert surface_fit(folded_v, folded_f, points, seed) < 1.1 * clean
    assert folded > weighed_fit(place(coarse.vertices), coarse.faces, points, seed) > clean
    band, f = _moebius(12, range(0))
    assert defect_share(place(band), f) == pytest.approx(2 / 24)


@pytest.mark.parametrize("seed", range(4))
def test_a_rival_of_fewer_faces_weighs_its_defects_by_area(seed):
    """At any pose and unit: a sphere less a random patch, the patch and a copy of it turned through it, with the
    faces far from the patch cut into four or left as they are: by area the defect share is the same either way
    (the crossing faces show as much) and the crossing faces' part of the area, so a rival that merges clean faces
    (an outline, a collapse) is not weighed farther than the mesh it came from; by faces the finer mesh weighs
    nearer.  ``weighed_fit`` reads the share by area when asked."""
    rng = np.random.default_rng(seed)
    pose = random_pose(rng)
    sphere = trimesh.creation.icosphere(2)
    axis = rng.normal(size=3)
    along = sphere.triangles_center @ (axis / np.linalg.norm(axis))
    patch = sphere.faces[along > 0.8]
    turned = sphere.vertices @ trimesh.transformations.rotation_matrix(0.3, rng.normal(size=3))[:3, :3].T
    coarse = trimesh.Trimesh(sphere.vertices, sphere.faces[along <= 0.8], process=False)
    fine = coarse.subdivide(face_index=np.flatnonzero(coarse.triangles_center @ axis / np.linalg.norm(axis) < 0.3))
    by_area, by_faces = [], []
    points = posed(trimesh.creation.icosphere(5).vertices, pose)
    for rest in (coarse, fine):  # the sphere's vertices first in both
        v = posed(np.concatenate([rest.vertices, turned]), pose)
        f = np.concatenate([rest.faces, patch, patch + len(rest.vertices)])
        bad, area = crossing_faces(v, f), triangle_areas(v, f)
        by_area.append(defect_share(v, f, by_area=True))
        by_faces.append(defect_share(v, f))
        weighed = weighed_fit(v, f, points, seed, by_area=True)
        share = defect_share(v, f, points, by_area=True)  # the fine mesh's cracks are holes too
        assert weighed == pytest.approx(surface_fit(v, f, points, seed) * (1 + DEFECT_WEIGHT * share))
        assert bad.any() and by_area[-1] == pytest.approx(area[bad].sum() / area.sum())
        assert by_faces[-1] == pytest.approx(bad.mean())
    assert len(fine.faces) > 1.5 * len(coarse.faces)
    assert by_area[1] == pytest.approx(by_area[0], rel=1e-6)
    assert by_faces[1] < 0.8 * by_faces[0]


@pytest.mark.parametrize("seed", range(4))
def test_a_hole_where_the_input_goes_on_weighs_and_the_inputs_own_border_does_not(seed):
    """At any pose and unit: a sphere with a random cap of faces taken out, against samples of the whole sphere,
    has the faces along the hole flagged (at least 90 % of them, no other), and weighs that share; the whole sphere
    has none, and the capped sphere against samples of itself (an open input: the opening is the input's own) at
    most a quarter of those along its rim (where the rim's teeth stand across a notch, the input goes on there)."""
    from fastmesh.faces.meshops import open_sides

    rng = np.random.default_rng(seed)
    rot = trimesh.transformations.random_rotation_matrix(rng.random(3))[:3, :3]
    scale, offset = 10.0 ** rng.uniform(-3, 3), rng.normal(size=3)
    place = lambda v: (np.asarray(v) @ rot.T + offset) * scale  # noqa: E731
    sphere = trimesh.creation.icosphere(3)
    v, f = place(sphere.vertices), np.asarray(sphere.faces)
    axis = rng.normal(size=3)
    cap = sphere.triangles_center @ (axis / np.linalg.norm(axis)) > rng.uniform(0.6, 0.9)
    holed = f[~cap]
    whole_input = place(trimesh.sample.sample_surface(sphere, 6000, seed=seed)[0])
    own_input = place(trimesh.sample.sample_surface(trimesh.Trimesh(sphere.vertices, holed), 6000, seed=seed)[0])
    flagged = hole_faces(v, holed, whole_input)
    along = open_sides(holed).reshape(3, -1).any(0)
    assert along.sum() >= 6 and not (flagged & ~along).any() and flagged.sum() >= 0.9 * along.sum()
    assert defect_share(v, holed, whole_input) == pytest.approx(flagged.mean())
    assert hole_faces(v, holed, own_input).sum() <= 0.25 * along.sum()
    assert not hole_faces(v, f, whole_input).any()
