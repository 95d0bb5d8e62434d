"""One request's input as the stages share it (fastmesh.request) and the face-count rule (facecount.count_rule)."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest
import trimesh

from fastmesh import request as request_module
from fastmesh.faces.facecount import count_rule
from fastmesh.params import GenerateParams
from fastmesh.pipeline import Pipeline
from fastmesh.request import PLANAR_SAMPLES, Frame, Request
from fastmesh.shapes.io import sample_surface
from fastmesh.shapes.shape import Shape


@pytest.fixture(scope="module")
def pipe():
    return Pipeline.from_pretrained(threads=1)


def _mesh() -> Shape:
    m = trimesh.creation.icosphere(3)
    m.apply_scale([1.0, 0.7, 0.5])
    return Shape(vertices=np.asarray(m.vertices), faces=np.asarray(m.faces))


def test_a_frame_draws_each_count_and_seed_once_and_as_sample_surface_does():
    shape = _mesh()
    frame = Frame.of(shape)
    a, b = frame.samples(500, 3), frame.samples(500, 3)
    assert a[0] is b[0] and a[1] is b[1]
    want = sample_surface(shape, 500, seed=3, vertices=frame.unit)
    assert np.array_equal(a[0], want[0]) and np.array_equal(a[1], want[1])
    assert not np.array_equal(frame.samples(500, 4)[0], a[0])
    turned = Frame.of(shape, trimesh.transformations.rotation_matrix(0.4, [1, 2, 3])[:3, :3])
    assert not np.allclose(turned.samples(500, 3)[0], a[0])


def test_a_point_cloud_frame_gives_its_own_points_as_the_surface():
    rng = np.random.default_rng(0)
    cloud = Shape(vertices=rng.normal(size=(300, 3)), normals=rng.normal(size=(300, 3)))
    frame = Frame.of(cloud)
    assert frame.surface(300, 0) is frame.unit or np.array_equal(frame.surface(300, 0), frame.unit)
    assert len(frame.surface(100, 0)) == 100


def test_a_request_reads_the_planar_draw_for_its_surface_points():
    shape = _mesh()
    req = Request.start(shape, GenerateParams())
    pts = req.surface_points
    assert np.array_equal(req.frame.norm.apply(pts).astype(np.float32), req.frame.samples(PLANAR_SAMPLES, 0)[0])


def test_the_count_rule_says_what_a_target_changes():
    free, held, told = count_rule(None), count_rule(300), count_rule(300, told=True)
    assert (free.low_poly_input, free.snap, free.remove_flat, free.hold) == (True, True, True, False)
    assert (held.low_poly_input, held.snap, held.remove_flat, held.hold) == (True, True, True, True)
    assert (told.low_poly_input, told.snap, told.remove_flat, told.hold) == (False, False, False, True)
    assert held.target == told.target == 300
    assert count_rule(None, told=True) == free


@pytest.mark.parametrize("target", [None, 400])
def test_a_mesh_job_draws_each_sample_once_and_reads_the_count_rule_once(pipe, monkeypatch, target):
    """A mesh input with two candidates: every (frame, count, seed) drawn once, the draws the plane rebuild, the
    cell evidence and the whole step share made once, and the face-count rule made once per request."""
    draws, rules = Counter(), []

    def counted(shape, n, seed=0, vertices=None):
        draws[(id(shape), n, seed)] += 1
        return sample_surface(shape, n, seed=seed, vertices=vertices)

    def rule(t, told=False):
        rules.append(t)
        return count_rule(t, told)

    monkeypatch.setattr(request_module, "sample_surface", counted)
    monkeypatch.setattr(request_module, "count_rule", rule)
    shape = _mesh()
    pipe.generate(shape, GenerateParams(seed=4, candidates=2, target_faces=target))
    assert rules == [target]
    assert draws and max(draws.values()) == 1
    own = {(n, seed) for key, n, seed in draws if key == id(shape)}
    assert (PLANAR_SAMPLES, 0) in own  # the cell evidence's (and, without a target, the planes' and whole step's)
    assert (pipe.triangle_config.support_points, 4) in own  # the candidates' reference and candidate 0's faces
