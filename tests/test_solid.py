"""The face stage's surface as the boundary of a solid (fastmesh.faces.solid): closed, wound outward, free of
self-intersections on closed shapes at any pose and scale; no fold where the surface selection folds; a sheet
stays open and faces its normals; the rival comes back where the cut loses the shape."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from fastmesh.evaluation.metrics import mesh_topology
from fastmesh.faces import mesh_from_adjacency
from fastmesh.faces import solid as sd
from fastmesh.faces.defects import self_intersections
from fastmesh.faces.meshops import edges_from_faces
from fastmesh.faces.triangles import TriangleConfig
from fastmesh.faces.winding import winding_numbers


def _sampled(m: trimesh.Trimesh, n: int = 8192, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    pts, fi = trimesh.sample.sample_surface(m, n, seed=seed)
    return np.asarray(pts), np.asarray(m.face_normals[fi])


def _shape(kind: str, rng: np.random.Generator) -> trimesh.Trimesh:
    if kind == "ellipsoid":
        m = trimesh.creation.icosphere(subdivisions=2)
        m.apply_scale(rng.uniform(0.3, 1.0, 3))
    elif kind == "box":
        m = trimesh.creation.box(rng.uniform(0.2, 1.0, 3)).subdivide()
    else:
        m = trimesh.creation.torus(1.0, rng.uniform(0.2, 0.4), major_sections=32, minor_sections=12)
    m.merge_vertices()
    return m


def _posed(m: trimesh.Trimesh, rng: np.random.Generator, scale: float) -> trimesh.Trimesh:
    m = m.copy()
    t = np.eye(4)
    t[:3, :3] = Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix() * scale
    t[:3, 3] = rng.uniform(-2, 2, 3) * scale
    m.apply_transform(t)
    return m


def _assert_solid_boundary(v: np.ndarray, f: np.ndarray, volume: float | None = None) -> None:
    """Every edge in two faces, wound oppositely (each directed edge once), outward, no self-intersection."""
    assert len(f)
    assert mesh_topology(v, f)["watertight"]
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    assert len(np.unique(directed, axis=0)) == len(directed)  # each edge once each way: wound oppositely
    vol = trimesh.Trimesh(v, f, process=False).volume
    assert vol > 0
    if volume is not None:
        assert vol == pytest.approx(volume, rel=0.02)
    assert self_intersections(v, f) == 0


@pytest.mark.parametrize("kind", ["ellipsoid", "box", "torus"])
@pytest.mark.parametrize("seed, scale", [(0, 1e-3), (1, 1.0), (2, 1e3)])
def test_closed_shapes_come_back_as_their_solid(kind, seed, scale):
    """Any rotation, millimetres to kilometres."""
    rng = np.random.default_rng(seed)
    m = _posed(_shape(kind, rng), rng, scale)
    pts, nrm = _sampled(m)
    v, f = sd.solid_surface(m.vertices, pts, nrm)
    _assert_solid_boundary(v, f, m.volume)


def test_inside_out_input_comes_back_outward():
    """An input wound inside-out (its normals point in: the winding number reads -1 inside) still gives the
    solid, wound outward."""
    m = _shape("torus", np.random.default_rng(1))
    pts, nrm = _sampled(m)
    v, f = sd.solid_surface(m.vertices, pts, -nrm)
    _assert_solid_boundary(v, f, m.volume)


@pytest.mark.parametrize("kind", ["thin_plate", "thin_ring"])
def test_no_fold_where_the_surface_selection_folds(kind):
    """Thin parts whose two sides lie within a sample spacing: the surface selection returns a closed mesh
    that folds through itself; the cut on the same vertices returns the thin solid."""
    if kind == "thin_plate":
        m = trimesh.creation.box((1.0, 1.0, 0.03)).subdivide().subdivide()
    else:
        m = trimesh.creation.torus(1.0, 0.03, major_sections=16, minor_sections=4)
    m.merge_vertices()
    pts, nrm = _sampled(m)
    v = np.asarray(m.vertices)
    cfg = TriangleConfig(close=True, close_everywhere=True)
    old_v, old_f = mesh_from_adjacency(v, edges_from_faces(np.asarray(m.faces)), cfg, points=pts)
    assert mesh_topology(old_v, old_f)["watertight"] and self_intersections(old_v, old_f) > 0
    new_v, new_f = sd.solid_surface(v, pts, nrm)
    _assert_solid_boundary(new_v, new_f, m.volume)


def test_winding_numbers_read_inside_and_outside():
    m = trimesh.creation.icosphere(subdivisions=3)
    pts, nrm = _sampled(m)
    # Queries 5 sample spacings (0.04) or more from the sphere: nearer, single dipoles show.
    q = np.array([[0, 0, 0], [0.5, 0.1, 0], [0, 0, 0.8], [0, 0, 1.2], [2, 0, 0], [0, 3, 1]], dtype=float)
    w = winding_numbers(q, pts, nrm)
    np.testing.assert_allclose(w, [1, 1, 1, 0, 0, 0], atol=0.05)


def test_min_cut_follows_cheap_faces():
    """Two cells that want inside joined to a third that barely wants outside by a dear face: all inside; by a
    cheap face: the third outside."""
    inside_cost = np.array([0.0, 0.0, 0.1])
    outside_cost = np.array([1.0, 1.0, 0.0])
    a, b = np.array([0, 1, 2]), np.array([1, 2, -1])
    dear = sd.min_cut(3, inside_cost, outside_cost, a, b, np.array([1.0, 5.0, 0.01]))
    cheap = sd.min_cut(3, inside_cost, outside_cost, a, b, np.array([1.0, 0.01, 0.01]))
    assert dear.tolist() == [True, True, True]
    assert cheap.tolist() == [True, True, False]


def test_rival_comes_back_where_the_cut_loses_the_shape():
    """A closed input whose vertices lie on one plane encloses nothing among them: the rival comes back, and the
    report says so."""
    m = trimesh.creation.box((1.0, 1.0, 1.0))
    pts, nrm = _sampled(m)
    flat = np.c_[np.random.default_rng(0).uniform(-0.5, 0.5, (30, 2)), np.zeros(30)]
    rival = (np.asarray(m.vertices), np.asarray(m.faces))
    v, f, report = sd.solid_mesh(flat, pts, nrm, None, None, rival, pts, 1.25)
    assert report["faces_from"] == "surface" and report["fits"]["solid"] is None
    assert f is rival[1]
    v, f, report = sd.solid_mesh(np.asarray(m.vertices), pts, nrm, None, None, rival, pts, 1.25)
    assert report["faces_from"] == "solid"
    _assert_solid_boundary(v, f, 1.0)


@pytest.mark.parametrize("seed", range(3))
def test_a_rival_nearer_the_input_but_folded_through_itself_loses_to_the_solid(seed):
    """The rival is weighed by what a renderer shows (``support.weighed_fit``): against a sphere's coarse solid,
    a rival lying nearer its input by more than the margin (the coarse sphere with a finer one turned through it,
    faces crossing) at any pose and unit.  By distance alone the rival would come back; the solid does, and the
    report holds the rival's weighed fit."""
    from fastmesh.faces.support import surface_fit, weighed_fit

    rng = np.random.default_rng(seed)
    t = np.eye(4)
    scale = 10.0 ** rng.uniform(-3, 3)
    t[:3, :3] = Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix() * scale
    t[:3, 3] = rng.uniform(-2, 2, 3) * scale
    turn = trimesh.transformations.rotation_matrix(float(rng.uniform(0.2, 0.4)), rng.normal(size=3))
    ball, coarse = trimesh.creation.icosphere(5).apply_transform(t), trimesh.creation.icosphere(1).apply_transform(t)
    fine = trimesh.creation.icosphere(2).apply_transform(turn).apply_transform(t)
    rival = (np.concatenate([coarse.vertices, fine.vertices]),
             np.concatenate([coarse.faces, fine.faces + len(coarse.vertices)]))
    pts, nrm = _sampled(ball)
    assert surface_fit(*rival, pts) * 1.1 < surface_fit(coarse.vertices, coarse.faces, pts)
    v, f, report = sd.solid_mesh(np.asarray(coarse.vertices), pts, nrm, None, None, rival, pts, 1.1)
    assert report["faces_from"] == "solid" and report["fits"]["surface"] == round(weighed_fit(*rival, pts), 6)
    _assert_solid_boundary(v, f)


def test_face_network_probabilities_make_cuts_cheap():
    """With the network's logits (an (N, N) matrix over the given vertices only): a triangle of predicted edges
    costs little, one of edges the network rules out its whole area, and one on a corner of the added box too."""
    m = trimesh.creation.box((1.0, 1.0, 1.0))
    v = np.asarray(m.vertices)
    logits = np.full((len(v), len(v)), -8.0)
    tri = np.array([[0, 1, 2], [0, 1, 3]])
    logits[0, 1] = logits[1, 0] = logits[1, 2] = logits[2, 1] = logits[0, 2] = logits[2, 0] = 8.0
    area = trimesh.triangles.area(v[tri])
    cost = sd.face_costs(v, tri, None, logits)
    assert cost[0] < 0.1 * area[0] and cost[1] > area[1]
    with_box = np.concatenate([v, [[5.0, 5.0, 5.0]]])
    corner = np.array([[0, 1, 8]])
    assert sd.face_costs(with_box, corner, None, logits)[0] > trimesh.triangles.area(with_box[corner])[0]
    pts, nrm = _sampled(m)
    out_v, out_f = sd.solid_surface(v, pts, nrm, None, logits)  # the box's corners beyond the logits' vertices
    _assert_solid_boundary(out_v, out_f, 1.0)


def test_parts_the_cut_loses_come_from_the_rival():
    """A box and, beside it, a plate thinner than the sample spacing whose vertices are one layer: the cut
    encloses the box and loses the plate (no thin-part vertices added).  Where the box alone lies over the margin
    from the input, the rival's plate faces are added as a piece of their own, made a slab as thick as the plate
    (its samples lie on both sides of the sheet), and the report counts them; where it fits (an unbounded
    margin), the solid comes back closed, with nothing patched in."""
    box = trimesh.creation.box((1.0, 1.0, 1.0))
    plate = trimesh.creation.box((1.0, 1.0, 0.004))
    plate.apply_translation((1.75, 0.0, 0.0))
    pts, nrm = _sampled(trimesh.util.concatenate([box, plate]))
    sheet_v = np.array([[1.25, -0.5, 0.0], [2.25, -0.5, 0.0], [2.25, 0.5, 0.0], [1.25, 0.5, 0.0]])
    v = np.concatenate([box.vertices, sheet_v])
    rival_f = np.concatenate([box.faces, np.array([[8, 9, 10], [8, 10, 11]])])
    out_v, out_f, report = sd.solid_mesh(v, pts, nrm, None, None, (v, rival_f), pts, 1.5, thin=False)
    assert report["faces_from"] == "solid" and report["patched_faces"] == 2
    # The plate's samples lie on both sides of the sheet: it comes back a slab as thick as the plate.
    assert report["slabs"] == 1 and len(out_f) == 12 + 2 * 2 + 4 * 2
    _assert_solid_boundary(out_v, out_f, 1.0 + 0.004)
    plate_v = out_v[out_v[:, 0] > 1.0]
    assert np.ptp(plate_v[:, 2]) == pytest.approx(0.004, rel=0.1)
    assert np.ptp(plate_v[:, 0]) == pytest.approx(1.0, rel=0.01)
    _, _, plain = sd.solid_mesh(v, pts, nrm, None, None, (v, rival_f), pts, 1.5, patch=False, thin=False)
    assert plain["patched_faces"] == 0 and plain["fits"]["solid"] > report["fits"]["solid"]
    assert plain["faces_from"] == "surface"
    whole_v, whole_f, whole = sd.solid_mesh(v, pts, nrm, None, None, (v, rival_f), pts, np.inf, thin=False)
    assert whole["faces_from"] == "solid" and whole["patched_faces"] == 0
    _assert_solid_boundary(whole_v, whole_f, 1.0)


def test_the_pipeline_reports_the_solid_stage_and_keeps_it_whole():
    """``TriangleConfig.solid``: each candidate's solid weighed in the face stage, ``info.solid_fits`` says which
    came back; where the solid did, no later step turns its edges or folds it.  It ships on; off (None), the
    report has no such entry."""
    import torch

    from fastmesh.evaluation.primitives import icosphere, point_cloud
    from fastmesh.params import GenerateParams
    from fastmesh.pipeline import Pipeline

    torch.set_num_threads(1)
    pipe = Pipeline.random(seed=0)
    cloud = point_cloud(icosphere(3), 4096, seed=0)
    assert TriangleConfig().solid is not None
    off = replace(pipe.triangle_config, solid=None)
    pipe.triangle_config, shipped = off, pipe.triangle_config
    assert "solid_fits" not in pipe.generate(cloud, GenerateParams(seed=0)).info
    pipe.triangle_config = replace(shipped, solid=np.inf)
    on = pipe.generate(cloud, GenerateParams(seed=0))
    report = on.info["solid_fits"]
    assert report["faces_from"] in ("solid", "surface") and set(report["fits"]) == {"solid", "surface"}
    if report["faces_from"] == "solid":
        assert "edges_turned" not in on.info and "redistribution_fits" not in on.info
        assert self_intersections(on.vertices, on.faces) == 0


def _tent_and_cap() -> tuple[np.ndarray, np.ndarray, trimesh.Trimesh]:
    """A unit box whose top is a tent raised to a far apex, a small cap box under the apex, and the input they
    stand for (the box and the cap): the apex's nearest input sample is on the cap's top, and moved there the
    tent's faces would pass through the cap."""
    corners = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)])
    body = trimesh.convex.convex_hull(np.concatenate([corners, [[0.0, 0.9, 0.0]]]))
    cap = trimesh.creation.box((0.16, 0.1, 0.16))
    cap.apply_translation((0.0, 0.6, 0.0))
    mesh = trimesh.util.concatenate([body, cap])
    box = trimesh.creation.box((1.0, 1.0, 1.0))
    return np.asarray(mesh.vertices), np.asarray(mesh.faces), trimesh.util.concatenate([box, cap])


def test_steps_after_the_solid_keep_it_free_of_folds(monkeypatch):
    """A solid result the pipeline's later steps would fold: ``whole`` pulls a vertex far from the input onto its
    nearest sample (``pieces.pull_in``), through another part.  Where the solid came back, the move is undone and
    the result stays free of self-intersections; the result of the surface selection is still pulled in."""
    import torch

    from fastmesh.params import GenerateParams
    from fastmesh.pipeline import Pipeline, candidate
    from fastmesh.shapes.shape import Normalization, Shape

    torch.set_num_threads(1)
    v, f, truth = _tent_and_cap()
    pts, nrm = _sampled(truth, 4096)
    cloud = Shape(vertices=pts, faces=None, normals=nrm)
    norm = Normalization.fit(pts)
    import fastmesh.pipeline as pipeline_module

    monkeypatch.setattr(pipeline_module, "canonical_rotation", lambda *a, **k: np.eye(3))
    for came_back in ("solid", "surface"):
        report = {"fits": {"solid": 1.0, "surface": 1.0}, "patched_faces": 0, "faces_from": came_back}
        monkeypatch.setattr(candidate, "solid_mesh", lambda *a, _r=report, **k: (norm.apply(v), f.copy(), _r))
        pipe = Pipeline.random(seed=0)
        pipe.triangle_config = replace(pipe.triangle_config, solid=np.inf)
        out = pipe.generate(cloud, GenerateParams(seed=0, closed="true"))
        assert out.info["solid_fits"]["faces_from"] == came_back
        assert (self_intersections(out.vertices, out.faces) == 0) == (came_back == "solid")
    assert self_intersections(v, f) == 0


def _thin_part_on_a_box(seed: int) -> tuple[np.ndarray, trimesh.Trimesh, trimesh.Trimesh]:
    """A unit box with a leg (a cylinder, even seeds) or a fin (a plate, odd seeds) 0.003-0.007 thick (under a
    cell of the vertex grid, 1/128) on its top; and the decoder's vertices: the box's corners and, on the thin
    part, one layer (its axis or its mid-plane)."""
    rng = np.random.default_rng(seed)
    thick, length = rng.uniform(0.003, 0.007), rng.uniform(0.4, 0.8)
    if seed % 2 == 0:
        part = trimesh.creation.cylinder(thick, length, sections=12)
        layer = np.stack([np.zeros(6), np.zeros(6), np.linspace(0.5, 0.5 + length, 6)], axis=1)
    else:
        part = trimesh.creation.box((length, thick, length))
        g = np.linspace(-length / 2, length / 2, 4)
        layer = np.array([[x, 0.0, 0.5 + z + length / 2] for x in g for z in g])
    part.apply_translation((0.0, 0.0, 0.5 + length / 2))
    body = trimesh.creation.box((1.0, 1.0, 1.0))
    return np.concatenate([body.vertices, layer]), part, trimesh.util.concatenate([body, part])


@pytest.mark.parametrize("seed", range(8))
def test_thin_parts_come_back_as_thin_closed_parts(seed):
    """Legs and fins thinner than a cell, at any pose, mm to km: the decoder's vertices are one layer across the
    part, so the cut alone loses it; with the input's samples there among the vertices it comes back a thin closed
    part of the solid: every sample of the part within 3 support limits of the result (no spike, nothing lost),
    the volume the input's (no web or blob), closed, wound outward, crossing nothing."""
    from fastmesh.faces.meshops import distance_to_triangles
    from fastmesh.faces.support import support_limit

    v, part, truth = _thin_part_on_a_box(seed)
    rng = np.random.default_rng(100 + seed)
    rot = Rotation.random(random_state=seed).as_matrix()
    scale = 10.0 ** rng.uniform(-3, 3)
    pts, nrm = _sampled(truth, 8192, seed)
    pts, nrm, v = pts @ rot.T * scale, nrm @ rot.T, v @ rot.T * scale
    on_part = trimesh.sample.sample_surface(part, 400, seed=seed)[0] @ rot.T * scale
    limit = support_limit(pts, 0.0)
    no_rival = (v, np.zeros((0, 3), dtype=np.int64))
    out_v, out_f, report = sd.solid_mesh(v, pts, nrm, None, None, no_rival, pts, np.inf, patch=False)
    assert report["faces_from"] == "solid" and report["thin_vertices"] > 0
    _assert_solid_boundary(out_v, out_f, truth.volume * scale**3)
    assert distance_to_triangles(on_part, out_v, out_f).max() < 3.0 * limit
    lost_v, lost_f, _ = sd.solid_mesh(v, pts, nrm, None, None, no_rival, pts, np.inf, patch=False, thin=False)
    assert distance_to_triangles(on_part, lost_v, lost_f).max() > 10.0 * limit  # the cut alone loses it


@pytest.mark.parametrize("lift", [0.0, 1e-9, 1e-6, 1e-4, 1e-3])
def test_a_flat_input_asked_closed_is_weighed_not_raised(lift):
    """A flat input (a square of samples) asked to be closed: its cells are flat or nearly so, and the cut, with
    or without thin-part vertices, may enclose nothing.  The stage weighs what it has (the rival where the solid
    is empty) and never samples a surface of no area."""
    rng = np.random.default_rng(int(lift * 1e9) % 97)
    pts = np.c_[rng.uniform(0, 1, (2000, 2)), np.zeros(2000)]
    nrm = np.tile([0.0, 0.0, 1.0], (2000, 1))
    v = np.c_[rng.uniform(0, 1, (30, 2)), rng.normal(0, lift, 30) if lift else np.zeros(30)]
    rival_f = np.array([[0, 1, 2], [1, 2, 3]])
    out_v, out_f, report = sd.solid_mesh(v, pts, nrm, None, None, (v, rival_f), pts, 1.1)
    assert report["faces_from"] in ("solid", "surface") and len(out_f)
    if report["fits"]["solid"] is None:
        assert report["faces_from"] == "surface" and np.array_equal(out_f, rival_f)


def test_a_solid_candidate_keeps_its_margin_against_the_other_candidates():
    """The solid comes back where it lies within ``TriangleConfig.solid`` times its own selection's fit; among
    candidates it keeps that allowance: a solid 5 % farther from the input than another candidate's selection is
    chosen over it at a margin of 1.1 (a clean closed mesh over a folded one), one 20 % farther is not."""
    from fastmesh.pipeline import Pipeline

    pipe = Pipeline.random(seed=0)
    pipe.triangle_config = replace(pipe.triangle_config, solid=1.1)
    solid = {"solid_fits": {"faces_from": "solid"}}
    surface = {"solid_fits": {"faces_from": "surface"}}
    assert pipe._allowed(solid, 1.05) < pipe._allowed(surface, 1.0)
    assert pipe._allowed(solid, 1.2) > pipe._allowed(surface, 1.0)
    assert pipe._allowed({}, 1.0) == 1.0
    pipe.triangle_config = replace(pipe.triangle_config, solid=None)
    assert pipe._allowed(solid, 1.05) == 1.05


@pytest.mark.parametrize("solid_open", [False, True])
def test_an_open_input_gets_the_solid_stage_with_solid_open(monkeypatch, solid_open):
    """``solid_open``: an input decided open (a half sphere: it encloses nothing) gets the solid stage too, each
    candidate weighed against its selection (``info.solid_fits``) and told the input is open; without it, the
    stage is not made for an open input."""
    import torch

    from fastmesh.params import GenerateParams
    from fastmesh.pipeline import Pipeline, candidate
    from fastmesh.shapes.shape import Shape

    torch.set_num_threads(1)
    calls = []
    real = candidate.solid_mesh
    monkeypatch.setattr(candidate, "solid_mesh", lambda *a, **k: calls.append(k.get("open_")) or real(*a, **k))
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(3000, 3))
    pts = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    pts[:, 2] = np.abs(pts[:, 2])
    cloud = Shape(vertices=pts, faces=None, normals=pts.copy())
    pipe = Pipeline.random(seed=0)
    pipe.triangle_config = replace(pipe.triangle_config, solid=1.1, solid_open=solid_open)
    out = pipe.generate(cloud, GenerateParams(seed=0))
    assert not out.info["closed_decision"]["close"] and len(out.faces)
    assert (len(calls) > 0) == solid_open == ("solid_fits" in out.info)
    assert all(calls)  # cut as a closed input's, then opened where the input is open (``uncapped``)
