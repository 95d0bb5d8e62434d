"""A result's faces spread over the input surface at its own count (``faces.redistribute``), kept by the pipeline
only where that lies nearer the input (``pipeline.result.redistributed``)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from fastmesh.evaluation.quality import topology
from fastmesh.faces.redistribute import redistribute
from fastmesh.faces.support import surface_fit
from fastmesh.faces.triangles import TriangleConfig
from fastmesh.params import GenerateParams
from fastmesh.pipeline import Pipeline
from fastmesh.pipeline import result as step8
from fastmesh.request import Request
from fastmesh.shapes.shape import Shape

torch.set_num_threads(1)

DATA = Path(__file__).parent / "data"


def _posed(mesh: trimesh.Trimesh, rng: np.random.Generator) -> trimesh.Trimesh:
    """``mesh`` turned at random, scaled by 10^-2 to 10^2 and moved up to 100 of its sizes from the origin."""
    scale = 10 ** rng.uniform(-2, 2)
    turn = trimesh.transformations.random_rotation_matrix(rng.random(3))[:3, :3]
    shift = rng.uniform(-100, 100, 3) * scale
    return trimesh.Trimesh(np.asarray(mesh.vertices) @ turn.T * scale + shift, mesh.faces, process=False)


def _torus(rng: np.random.Generator) -> tuple[trimesh.Trimesh, trimesh.Trimesh]:
    """A torus of random radii finely made, and the same torus with few sections around its ring and many
    around its tube: long faces whose chords cut across the ring's curve, as the decoder spans a limb."""
    major, minor = rng.uniform(0.3, 0.45), rng.uniform(0.04, 0.12)
    rings, tubes = int(rng.integers(6, 11)), int(rng.integers(16, 25))
    fine = trimesh.creation.torus(major, minor, major_sections=128, minor_sections=64)
    poor = trimesh.creation.torus(major, minor, major_sections=rings, minor_sections=tubes)
    state = rng.bit_generator.state
    fine = _posed(fine, rng)
    rng.bit_generator.state = state  # the same pose for both
    return fine, _posed(poor, rng)


def _samples(mesh: trimesh.Trimesh, n: int = 8192) -> tuple[np.ndarray, np.ndarray]:
    points, index = trimesh.sample.sample_surface(mesh, n, seed=0)
    return np.asarray(points), np.asarray(mesh.face_normals[index])


def test_faces_move_from_a_tubes_straight_sides_to_its_ring_on_a_random_family():
    """Tori of random radii, poses and units, made with too few sections around the ring: redistributed, each
    keeps its face count, stays closed, edge-manifold and of one piece with a torus's Euler characteristic (0),
    and lies nearer the input than before (``support.surface_fit``, its Chamfer part at least 10 % nearer)."""
    rng = np.random.default_rng(7)
    for _ in range(6):
        fine, poor = _torus(rng)
        points, normals = _samples(fine)
        v, f = redistribute(poor.vertices, poor.faces, points, normals)
        t = topology(f)
        assert len(f) == len(poor.faces)
        assert t["watertight"] and t["non_manifold_edges"] == 0 and t["pieces"] == 1
        assert len(np.unique(f)) - len(trimesh.Trimesh(v, f, process=False).edges_unique) + len(f) == 0
        before = surface_fit(poor.vertices, poor.faces, points, hausdorff_weight=0.0)
        after = surface_fit(v, f, points, hausdorff_weight=0.0)
        assert after < 0.9 * before, (before, after)


def test_a_point_clouds_result_comes_back_redistributed_only_where_nearer():
    """``step8.redistributed`` gives the spread mesh back exactly where its fit beats the result's: the poor
    torus's comes back, a box's and an icosphere's own faces (nothing to move) stay; a mesh input is weighed
    against its decimation instead and is never redistributed."""
    rng = np.random.default_rng(3)
    fine, poor = _torus(rng)
    cases = [(fine, poor), (trimesh.creation.box((1.0, 2.0, 0.5)),) * 2, (trimesh.creation.icosphere(2),) * 2]
    kept = []
    for source, result in cases:
        points, normals = _samples(source)
        req = Request.start(Shape(vertices=points, normals=normals), GenerateParams())
        rival, fits = step8.redistributed(req, np.asarray(result.vertices), np.asarray(result.faces), 2.0, 4096)
        assert (rival is not None) == (fits["redistributed"] < fits["model"])
        kept.append(rival is not None)
        if rival is not None:
            assert len(rival[1]) == len(result.faces) and topology(rival[1])["watertight"]
    assert kept == [True, False, False]
    mesh = Request.start(Shape(vertices=np.asarray(fine.vertices), faces=np.asarray(fine.faces)), GenerateParams())
    assert step8.redistributed(mesh, np.asarray(poor.vertices), np.asarray(poor.faces), 2.0, 4096) == (None, {})


@pytest.fixture(scope="module")
def pipe() -> Pipeline:
    return Pipeline.random(seed=0)


def test_the_pipeline_weighs_a_point_clouds_result_and_reports_both_fits(pipe, monkeypatch):
    """With ``TriangleConfig.redistribute`` (the shipped default; the random pipeline's meshes are not worth it)
    a point cloud's result is weighed against its redistribution, and ``info`` holds both fits; the result that
    comes back is the one the fits name."""
    assert TriangleConfig().redistribute == 2.0 and pipe.triangle_config.redistribute is None
    # The surface selection's result: a solid is never redistributed (``test_solid``).
    monkeypatch.setattr(pipe, "triangle_config", replace(pipe.triangle_config, redistribute=2.0, solid=None))
    sphere = trimesh.creation.icosphere(3)
    points, normals = _samples(sphere, 2048)
    seen = []
    monkeypatch.setattr(step8, "redistribute", lambda v, f, *a, **k: seen.append(len(f)) or (v * 1.5, f))
    res = pipe.generate(Shape(vertices=points, normals=normals), GenerateParams(max_vertices=48, seed=1))
    fits = res.info["redistribution_fits"]
    assert seen and fits["model"] < fits["redistributed"]  # blown up by half: farther, not taken
    assert len(res.faces) == seen[0]


def test_a_result_with_split_pinches_stays_edge_manifold_once_welded():
    """A generated wheel, closed, with 25 pinches split into two vertices at one position (``pieces.split_pinches``,
    as the pipeline gives them): its redistribution (``step8.spread``), welded by position, has no edge of
    three faces and stays closed (collapses that saw each copy apart from the other would make two)."""
    from fastmesh.evaluation.metrics import mesh_topology

    data = np.load(DATA / "pinched_wheel.npz")
    v, f = data["vertices"].astype(np.float64), data["faces"].astype(np.int64)
    assert len(v) - len(np.unique(v, axis=0)) == 25 and mesh_topology(v, f)["watertight"]
    rival = step8.spread(v, f, data["points"].astype(np.float64), data["normals"].astype(np.float64), 2.0)
    assert rival is not None
    t = mesh_topology(*rival)
    assert t["edge_manifold"] and t["watertight"] and len(rival[1]) == len(f)


def test_a_redistribution_that_would_break_the_surface_is_not_weighed(monkeypatch):
    """Whatever the redistribution gives, one with an edge of three faces, or open where the result is closed,
    never comes back, however near."""
    sphere = trimesh.creation.icosphere(2)
    points, normals = _samples(sphere)
    assert step8.spread(sphere.vertices, sphere.faces, points, normals, 2.0) is not None
    v, f = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    fin = np.concatenate([f, [[f[0, 0], f[0, 1], int(np.setdiff1d(np.arange(len(v)), f[:2].ravel())[0])]]])
    for broken in (fin, f[1:]):  # a fin on an edge; a face off
        monkeypatch.setattr(step8, "redistribute", lambda *a, b=broken, **k: (v, b))
        assert step8.spread(v, f, points, normals, 2.0) is None
