"""Closure (fastmesh.faces.closure): deciding from the input whether to close, and closing what step 6 left open."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from fastmesh.evaluation.primitives import point_cloud
from fastmesh.evaluation.quality import topology
from fastmesh.faces import closure
from fastmesh.faces.closure import _winding, close_loops, decide_closed, mesh_open_share, winding_closed_share
from fastmesh.faces.orient import orient_faces
from fastmesh.faces.selection import Selection
from fastmesh.faces.support import support_limit
from fastmesh.faces.surface_triangles import vertex_frames
from fastmesh.shapes.io import sample_surface
from fastmesh.shapes.shape import Shape


def _closed_shapes(rng: np.random.Generator) -> list[trimesh.Trimesh]:
    """Closed meshes of random proportions, sizes and turns."""
    out = []
    for make in (lambda: trimesh.creation.box(extents=rng.uniform(0.2, 1.0, 3)),
                 lambda: trimesh.creation.icosphere(2),
                 lambda: trimesh.creation.cylinder(radius=rng.uniform(0.2, 1.0), height=rng.uniform(0.2, 2.0)),
                 lambda: trimesh.creation.torus(1.0, rng.uniform(0.2, 0.5))):
        m = make()
        m.apply_scale(rng.uniform(0.8, 1.2, 3) * 10 ** rng.uniform(-2, 2))
        m.apply_transform(trimesh.transformations.random_rotation_matrix(rng.random(3)))
        out.append(m)
    return out


def _open_shapes(rng: np.random.Generator) -> list[trimesh.Trimesh]:
    """Open meshes: a hemisphere, a wavy sheet, a box without its top."""
    sphere = trimesh.creation.icosphere(3)
    hemi = sphere.submesh([np.flatnonzero(sphere.triangles_center[:, 2] > 0.1)], append=True)
    x, y = np.meshgrid(np.linspace(0, 1, 20), np.linspace(0, 1, 20))
    z = 0.1 * np.sin(6 * x + rng.uniform(0, 3)) * np.cos(4 * y)
    grid = np.c_[x.ravel(), y.ravel(), z.ravel()]
    i = np.arange(19 * 20).reshape(19, 20)[:, :19].ravel()
    sheet = trimesh.Trimesh(grid, np.r_[np.c_[i, i + 1, i + 20], np.c_[i + 1, i + 21, i + 20]])
    box = trimesh.creation.box(extents=rng.uniform(0.3, 1.0, 3))
    lidless = box.submesh([np.flatnonzero(box.face_normals[:, 2] < 0.5)], append=True)
    return [hemi, sheet, lidless]


def _shape(m: trimesh.Trimesh) -> Shape:
    return Shape(vertices=np.asarray(m.vertices, dtype=np.float64), faces=np.asarray(m.faces, dtype=np.int64))


def test_closed_meshes_and_point_clouds_are_told_from_open_ones():
    rng = np.random.default_rng(0)
    for m in _closed_shapes(rng):
        assert decide_closed(_shape(m)) == (True, "closed_mesh")
        cloud = point_cloud(_shape(m), 4000, seed=1)
        assert decide_closed(cloud) == (True, "closed_points")
        # Normals that all point inwards enclose the volume as well.
        inward = Shape(vertices=cloud.vertices, normals=-cloud.normals)
        assert decide_closed(inward) == (True, "closed_points")
    for m in _open_shapes(rng):
        assert decide_closed(_shape(m)) == (False, "open_mesh")
        assert decide_closed(point_cloud(_shape(m), 4000, seed=1)) == (False, "open_points")


def test_a_closed_mesh_split_at_its_seams_is_closed_and_asking_overrides():
    box = trimesh.creation.box()
    split = Shape(vertices=box.vertices[box.faces].reshape(-1, 3), faces=np.arange(36).reshape(-1, 3))
    assert topology(split.faces)["boundary_edges"] == 36 and mesh_open_share(split.vertices, split.faces) == 0.0
    assert decide_closed(split) == (True, "closed_mesh")
    assert decide_closed(split, "false") == (False, "asked")
    sheet = _shape(_open_shapes(np.random.default_rng(1))[1])
    assert decide_closed(sheet, "true") == (True, "asked")
    assert decide_closed(Shape(vertices=np.random.default_rng(2).random((100, 3)))) == (False, "open_points")
    with pytest.raises(ValueError, match="closed must be one of"):
        decide_closed(sheet, "yes")


@pytest.mark.parametrize("seed", range(4))
def test_a_dense_mesh_with_a_wide_opening_is_open_and_one_with_small_holes_closed(seed):
    """The decision does not hang on the density: a box drawn at random without its lid, split into so many faces
    that under 1 % of its edges are on the opening, is open; its openings' area is the lid's.  The closed box of
    the same density with a face taken out here and there (cracks a scan leaves) is closed."""
    rng = np.random.default_rng(seed)
    ext = rng.uniform(0.2, 1.0, 3) * 10.0 ** rng.uniform(-2, 2)
    box = trimesh.creation.box(extents=ext)
    box.apply_transform(trimesh.transformations.random_rotation_matrix(rng.random(3)))
    top = np.argmax(np.abs(box.face_normals @ box.vertices[0]))  # any one side serves as the lid
    side = np.abs(box.face_normals @ box.face_normals[top]) > 0.99
    lid = side & (box.face_normals @ box.face_normals[top] > 0)
    v, f = trimesh.remesh.subdivide_to_size(box.vertices, box.faces[~lid], ext.max() / 40)
    open_box = Shape(vertices=v, faces=f)
    assert 0 < mesh_open_share(v, f) <= closure.OPEN_SHARE
    lid_area = box.area_faces[lid].sum()
    assert closure.opening_area_share(v, f) == pytest.approx(lid_area / (box.area - lid_area), rel=1e-6)
    assert decide_closed(open_box) == (False, "open_mesh")
    v, f = trimesh.remesh.subdivide_to_size(box.vertices, box.faces, ext.max() / 40)
    cracked = np.delete(f, rng.choice(len(f), 5, replace=False), axis=0)
    assert closure.opening_area_share(v, cracked) < closure.HOLE_AREA_SHARE
    assert decide_closed(Shape(vertices=v, faces=cracked)) == (True, "closed_mesh")


def test_winding_numbers_match_the_sum_over_dipoles():
    """``_winding`` (products of (Q, 3) by (3, N)) against its slow twin, the dipoles' sum taken pair by
    pair, at queries near and far from the points."""
    rng = np.random.default_rng(2)
    pts, nrm = sample_surface(_shape(trimesh.creation.icosphere(3)), 3000, seed=1)
    pts, nrm = pts.astype(np.float64), nrm.astype(np.float64)
    area = rng.uniform(1e-4, 2e-3, len(pts))
    queries = np.concatenate([pts[:300] * 0.98, pts[300:600] * 1.02, rng.uniform(-2, 2, (300, 3))])
    d = pts[None] - queries[:, None]
    slow = (area * np.einsum("qni,ni->qn", d, nrm) / np.linalg.norm(d, axis=2) ** 3).sum(1) / (4 * np.pi)
    np.testing.assert_allclose(_winding(queries, pts, nrm, area), slow, rtol=1e-9, atol=1e-9)


def test_winding_share_is_high_inside_a_sphere_and_low_on_a_disc():
    sphere = point_cloud(_shape(trimesh.creation.icosphere(3)), 3000)
    assert winding_closed_share(sphere.vertices, sphere.normals) > 0.85
    rng = np.random.default_rng(3)
    r, t = np.sqrt(rng.random(3000)), rng.uniform(0, 2 * np.pi, 3000)
    disc = np.c_[r * np.cos(t), r * np.sin(t), np.zeros(3000)]
    assert winding_closed_share(disc, np.tile([0.0, 0.0, 1.0], (3000, 1))) < 0.05


def _holed(m: trimesh.Trimesh, rng: np.random.Generator, holes: int) -> np.ndarray:
    """``m``'s faces less those around ``holes`` random vertices (each hole the vertex's fan)."""
    f = np.asarray(m.faces)
    gone = np.zeros(len(f), dtype=bool)
    for v in rng.choice(len(m.vertices), size=holes, replace=False):
        gone |= (f == v).any(1)
    return f[~gone]


def _book(v: np.ndarray, f: np.ndarray, pts: np.ndarray) -> Selection:
    book = Selection(v, vertex_frames(v, pts, cKDTree(pts)), 30.0)
    for t in f.tolist():
        book.add(*t)
    return book


@pytest.mark.parametrize("seed", range(4))
def test_close_loops_joins_the_fans_of_a_pinched_vertex(seed):
    """Faces taken out at random leave vertices whose faces form two fans with the hole on either side;
    closing the holes joins the fans (split at such a vertex, each loop would close its fan into a cone)."""
    rng = np.random.default_rng(seed)
    m = trimesh.creation.icosphere(2)
    v = np.asarray(m.vertices)
    f = orient_faces(v, np.asarray(m.faces)[rng.random(len(m.faces)) > 0.12])
    pts = sample_surface(_shape(m), 4000, seed=seed)[0].astype(np.float64)
    assert topology(f)["non_manifold_vertices"] > 0
    closed = orient_faces(v, close_loops(v, f, _book(v, f, pts), pts, support_limit(pts, 0.0))[1])
    top = topology(closed)
    assert top["watertight"] and top["non_manifold_vertices"] == 0 and top["pieces"] == 1


@pytest.mark.parametrize("seed", range(4))
def test_close_loops_closes_random_holes_and_stays_a_surface(seed):
    rng = np.random.default_rng(seed)
    m = trimesh.creation.icosphere(2)
    m.apply_scale(rng.uniform(0.5, 1.5, 3))
    v = np.asarray(m.vertices)
    f = orient_faces(v, _holed(m, rng, 5))
    pts = sample_surface(_shape(m), 4000, seed=seed)[0].astype(np.float64)
    assert topology(f)["boundary_edges"] > 0
    closed = orient_faces(v, close_loops(v, f, _book(v, f, pts), pts, support_limit(pts, 0.0))[1])
    top = topology(closed)
    assert top["watertight"] and top["non_manifold_edges"] == 0 and top["pieces"] == 1
    assert len(np.unique(np.sort(closed, axis=1), axis=0)) == len(closed)  # no face twice
    assert trimesh.Trimesh(v, closed).is_winding_consistent


def test_close_loops_leaves_a_closed_surface_and_longer_loops_alone():
    m = trimesh.creation.icosphere(2)
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    pts = sample_surface(_shape(m), 4000)[0].astype(np.float64)
    same = close_loops(v, f, _book(v, f, pts), pts, support_limit(pts, 0.0))[1]
    assert np.array_equal(np.sort(same, axis=1), np.sort(f, axis=1))
    hemi = f[m.triangles_center[:, 2] > 0.0]  # one loop of many edges: over the limit, left open
    loop = topology(hemi)["boundary_edges"]
    out = close_loops(v, hemi, _book(v, hemi, pts), pts, support_limit(pts, 0.0), max_loop=loop - 1)[1]
    assert len(out) == len(hemi)


def test_an_opening_of_the_input_stays_open():
    """A sphere with its top cut off, and only its samples: a cap over the rim would cross the opening (each
    of its triangles has most of its area near the rim, its middle far from every input point)."""
    m = trimesh.creation.icosphere(2)
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    hemi = f[m.triangles_center[:, 2] < 0.6]
    pts = sample_surface(Shape(vertices=v, faces=hemi), 4000)[0].astype(np.float64)
    assert len(close_loops(v, hemi, _book(v, hemi, pts), pts, support_limit(pts, 0.0))[1]) == len(hemi)


def test_without_bounds_every_loop_closes_however_far_its_cap_strays():
    """A closed mesh input has no openings (``TriangleConfig.close_everywhere``): the cap the bounded closure
    refuses above is taken, and the result is watertight and edge-manifold, for caps of random heights."""
    rng = np.random.default_rng(4)
    m = trimesh.creation.icosphere(2)
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    for cut in rng.uniform(0.4, 0.8, 3):
        part = f[m.triangles_center[:, 2] < cut]
        pts = sample_surface(Shape(vertices=v, faces=part), 4000)[0].astype(np.float64)
        limit = support_limit(pts, 0.0)
        assert len(close_loops(v, part, _book(v, part, pts), pts, limit)[1]) == len(part)
        out_v, out_f = close_loops(v, part, _book(v, part, pts), pts, limit, bounded=False)
        top = topology(orient_faces(out_v, out_f))
        assert top["watertight"] and top["non_manifold_vertices"] == 0


def test_a_loop_no_triangulation_closes_gets_a_fan_about_an_input_point(monkeypatch):
    """Where no triangulation of a loop's own vertices fits, the loop is joined to a new vertex: the input
    point nearest its middle.  (The triangulations are refused here to reach that step.)"""
    import fastmesh.faces.closure as closure

    monkeypatch.setattr(closure, "_close_loop", lambda *a, **k: None)
    monkeypatch.setattr(closure, "_best_triangulation", lambda *a, **k: None)
    rng = np.random.default_rng(5)
    m = trimesh.creation.icosphere(3)
    v = np.asarray(m.vertices)
    f = orient_faces(v, _holed(m, rng, 4))
    pts = sample_surface(_shape(m), 6000, seed=1)[0].astype(np.float64)
    holes = len(closure.hole_loops(v, f))
    out_v, out_f = close_loops(v, f, _book(v, f, pts), pts, support_limit(pts, 0.0))
    top = topology(orient_faces(out_v, out_f))
    assert top["watertight"] and top["non_manifold_vertices"] == 0 and len(out_v) == len(v) + holes
    assert np.isin(out_v[len(v):], pts).all(1).all()  # the new vertices are input points


@pytest.mark.parametrize(("holed", "closed", "everywhere"),
                         [(False, "auto", True), (False, "true", True), (True, "auto", False), (True, "true", False)])
def test_the_pipeline_closes_everywhere_only_for_a_closed_mesh(monkeypatch, holed, closed, everywhere):
    """A closed mesh input has no openings, whether ``closed`` is decided or asked; one with a hole, even asked
    to close, keeps the closure's reach."""
    import fastmesh.pipeline.candidate as candidate
    from fastmesh.params import GenerateParams
    from fastmesh.pipeline import Pipeline

    seen = []

    def spy(positions, edges, config, **kw):
        seen.append(config.close_everywhere)
        return real(positions, edges, config, **kw)

    real = candidate.mesh_from_adjacency
    monkeypatch.setattr(candidate, "mesh_from_adjacency", spy)
    m = trimesh.creation.icosphere(2)
    faces = np.asarray(m.faces)[m.triangles_center[:, 2] < 0.9] if holed else np.asarray(m.faces)
    Pipeline.random().generate(Shape(vertices=np.asarray(m.vertices), faces=faces),
                               GenerateParams(seed=0, closed=closed, max_vertices=48))
    assert seen and set(seen) == {everywhere}
