"""A result that must be closed is closed, or its report says it is not and why: ``closed=true`` on a low-poly
input of two shells whose seams lie 0.2 % apart closes it; ``closed_decision`` is never "closed" on a result with
open edges or edges of three or more faces.  A low-poly input comes back as itself before any network runs."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh
from lowpoly import jittered, two_shells

from fastmesh.evaluation.primitives import point_cloud
from fastmesh.faces.closure import decide_closed
from fastmesh.faces.triangles import TriangleConfig
from fastmesh.params import GenerateParams
from fastmesh.pipeline import Pipeline
from fastmesh.pipeline import result as step8
from fastmesh.pipeline.closing import closed_result, weld_seams
from fastmesh.request import Request
from fastmesh.shapes.io import sample_surface
from fastmesh.shapes.shape import Shape

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def pipe() -> Pipeline:
    return Pipeline.random(seed=0)


@pytest.fixture
def no_networks(pipe, monkeypatch) -> Pipeline:
    """``pipe`` whose networks fail the test if anything runs them (``_in_frames`` runs every one of them)."""

    def ran(*args, **kwargs):
        raise AssertionError("the networks ran")

    monkeypatch.setattr(Pipeline, "_in_frames", ran)
    return pipe


def open_edges(faces: np.ndarray) -> int:
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return int((counts == 1).sum())


def test_seams_a_fraction_of_a_cell_apart_are_welded():
    shells = two_shells(segments=12)
    assert open_edges(shells.faces) == 24
    v, f = weld_seams(shells.vertices / 2.0, shells.faces)  # the unit cube: the egg is 2 tall
    assert open_edges(f) == 0 and len(f) == len(shells.faces) and len(v) == len(shells.vertices) - 12
    far = two_shells(segments=12, gap=0.05)  # 5 % apart: an opening, not a seam
    assert open_edges(weld_seams(far.vertices / 2.0, far.faces)[1]) == 24


def test_closed_true_closes_two_shells_without_the_networks(no_networks):
    """The low-poly egg of two open shells comes back as itself, closed, and no network runs for it."""
    shells = two_shells(segments=12)
    res = no_networks.generate(shells, GenerateParams(closed="true"))
    assert res.info["result_from"] == "input" and res.tokens == 0
    q = res.quality
    assert q["boundary_edges"] == 0 and q["non_manifold_edges"] == 0 and q["watertight"]
    assert q["closed_decision"] == "asked" and res.info["notes"] == []
    assert len(res.faces) == len(shells.faces) and q["hd"] < 0.5  # its own faces, the seam closed where it lay


@pytest.mark.parametrize("name", ["icosphere", "cylinder", "torus"])
def test_a_low_poly_input_comes_back_before_the_networks(no_networks, name):
    mesh = {"icosphere": trimesh.creation.icosphere(1), "cylinder": trimesh.creation.cylinder(0.5, 2.0, sections=16),
            "torus": trimesh.creation.torus(1.0, 0.3, major_sections=8, minor_sections=6)}[name]
    shape = jittered(mesh)
    assert len(shape.faces) > 32  # more than the networks were skipped for before
    res = no_networks.generate(shape, GenerateParams())
    assert res.info["result_from"] == "input" and len(res.faces) == len(shape.faces)
    assert res.timings["vertices"] == 0.0 and res.quality["closed_decision"] == "closed"


def test_a_result_to_be_closed_that_is_open_is_reported_so():
    """A sphere's points read as closed; a result with a hole cut in it, lying off the input (a third larger: no
    cap of it lies on the input within the face stage's limit), is reported ``not_closed``, with a note."""
    ball = trimesh.creation.icosphere(2)
    pts, nrm = sample_surface(Shape(vertices=np.asarray(ball.vertices), faces=np.asarray(ball.faces)), 4000, seed=0)
    points = Shape(vertices=pts.astype(np.float64), normals=nrm.astype(np.float64))
    cut = np.asarray(ball.faces)[ball.vertices[ball.faces].mean(axis=1)[:, 1] < 0.6]  # its top cut off
    for closed in ("auto", "true"):
        req = Request.start(points, GenerateParams(closed=closed))
        req.close, req.reason = decide_closed(req.shape, closed)
        assert req.close
        v, f, note = closed_result(req, 1.3 * np.asarray(ball.vertices), cut, TriangleConfig())
        assert note is not None and "open edges" in note and len(f) == len(cut)
        res = step8.finished(req, v, f, tokens=0, info={}, note=note)
        assert res.quality["boundary_edges"] > 0 and res.quality["closed_decision"] == "not_closed"
        assert res.info["notes"][0] == note
        assert ("closed=true was asked" if closed == "true" else "reads as closed (closed_points)") in note
        # Without the closing step's note, the report still says what stays open.
        bare = step8.finished(req, v, f, tokens=0, info={})
        assert bare.quality["closed_decision"] == "not_closed" and "open edges" in bare.info["notes"][0]


def test_no_report_claims_a_closed_mesh_that_is_not(pipe):
    """Over inputs of several kinds the tiny networks make what they make; whatever it is, "closed" holds."""
    sphere = trimesh.creation.icosphere(3)
    ball = point_cloud(Shape(vertices=np.asarray(sphere.vertices), faces=np.asarray(sphere.faces)), 2000)
    for shape in (ball, two_shells(segments=26, rings=2), jittered(trimesh.creation.icosphere(3))):
        for closed in ("auto", "true"):
            res = pipe.generate(shape, GenerateParams(seed=1, closed=closed, max_vertices=40))
            q = res.quality
            if q["closed_decision"] == "closed" or (closed == "true" and q["closed_decision"] == "asked"):
                assert q["boundary_edges"] == 0 and q["non_manifold_edges"] == 0, q
            else:
                assert q["closed_decision"] in ("open", "not_closed"), q
            if q["closed_decision"] == "not_closed":
                assert any("open edges" in n or "three or more" in n for n in res.info["notes"])


def test_shipped_networks_close_the_shells_or_say_why():
    """The issue's case with the shipped weights: two shells of 260 faces (more than are given back unrun) whose
    seams lie 0.2 % apart, ``closed=true``: before, the input came back with its 52 open edges and no word."""
    pipe = Pipeline.from_pretrained()
    res = pipe.generate(two_shells(segments=26, rings=2), GenerateParams(closed="true"))
    q = res.quality
    assert (q["boundary_edges"] == 0 and q["non_manifold_edges"] == 0) or res.info["notes"], (q, res.info["notes"])
    assert q["boundary_edges"] == 0  # the seams weld
