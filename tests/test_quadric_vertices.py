"""A mesh input's chosen mesh weighed against the face stage's mesh on the vertices of the input's quadric
decimation (``TriangleConfig.quadric_vertices``, ``pipeline.candidate``)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import cKDTree

from fastmesh.faces.decimation import quadric_decimation
from fastmesh.faces.triangles import TriangleConfig
from fastmesh.params import GenerateParams
from fastmesh.pipeline import Pipeline
from fastmesh.pipeline.candidate import CandidateSteps
from fastmesh.shapes.shape import Shape

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def pipe() -> Pipeline:
    return Pipeline.random(seed=0)


def _dense(rng: np.random.Generator) -> trimesh.Trimesh:
    """A capsule, a torus or an ellipsoid of random proportions, a few thousand faces, turned, scaled by 10^-2 to
    10^2 and moved up to 100 of its sizes from the origin."""
    kind = rng.integers(3)
    if kind == 0:
        mesh = trimesh.creation.capsule(rng.uniform(0.5, 1.5), rng.uniform(0.2, 0.5), count=[24, 24])
    elif kind == 1:
        mesh = trimesh.creation.torus(1.0, rng.uniform(0.2, 0.5), major_sections=32, minor_sections=16)
    else:
        mesh = trimesh.creation.icosphere(4)
        mesh.vertices *= rng.uniform(0.3, 1.0, 3)
    scale = 10 ** rng.uniform(-2, 2)
    turn = trimesh.transformations.random_rotation_matrix(rng.random(3))[:3, :3]
    shift = rng.uniform(-100, 100, 3) * scale
    return trimesh.Trimesh(np.asarray(mesh.vertices) @ turn.T * scale + shift, mesh.faces, process=False)


def _spy(monkeypatch) -> list:
    """Every call of ``CandidateSteps._with_quadrics``, as (frame, the mesh it weighed, what it returned)."""
    calls, weigh = [], CandidateSteps._with_quadrics

    def spy(self, req, frame, best):
        out = weigh(self, req, frame, best)
        calls.append((frame, best, out))
        return out

    monkeypatch.setattr(CandidateSteps, "_with_quadrics", spy)
    return calls


def test_the_quadrics_vertices_come_back_exactly_where_their_mesh_lies_nearer(pipe, monkeypatch):
    """Dense meshes of random kinds, proportions, poses and units, with ``TriangleConfig.quadric_vertices`` (the
    shipped default; the random pipeline's meshes are not worth it): in every frame the mesh on the quadrics'
    vertices replaces the decoder's exactly where its fit is lower; it is made of the vertices of the input's
    decimation to the decoder's face count, and nothing else; the result's ``info`` names where its vertices come
    from with both fits.  A random decoder's meshes lie far from the input: the quadrics' are nearer."""
    assert TriangleConfig().quadric_vertices and not pipe.triangle_config.quadric_vertices
    # The surface selection's meshes (the solid's, with its thin-part vertices, may have more faces than the budget's
    # decimation has vertices for).
    monkeypatch.setattr(pipe, "triangle_config", replace(pipe.triangle_config, quadric_vertices=True, solid=None))
    calls = _spy(monkeypatch)
    rng = np.random.default_rng(5)
    chosen = 0
    for i in range(4):
        mesh = _dense(rng)
        calls.clear()
        res = pipe.generate(Shape(vertices=mesh.vertices, faces=mesh.faces),
                            GenerateParams(max_vertices=40, seed=i, temperature=1.0))
        assert calls
        for frame, best, out in calls:
            fits = out["quadric_fits"]
            assert (out["vertices_from"] == "quadrics") == (fits["quadrics"] < fits["decoder"])
            if out["vertices_from"] == "decoder":
                assert out["vertices"] is best["vertices"]
                continue
            chosen += 1
            decimated, _ = quadric_decimation(frame.unit, frame.shape.faces, len(best["faces"]))
            assert cKDTree(decimated).query(out["positions"])[0].max() < 1e-9
            assert cKDTree(decimated).query(out["vertices"])[0].max() < 1e-9
        assert res.info["vertices_from"] in {out["vertices_from"] for _, _, out in calls}
        assert res.info["quadric_fits"] in [out["quadric_fits"] for _, _, out in calls]
    assert chosen > 0  # the case this is here for


def test_point_clouds_and_the_pipeline_without_it_keep_the_decoders_vertices(pipe, monkeypatch):
    """A point cloud has no quadrics: its vertices come from the decoder and nothing is weighed; nor is anything
    weighed with ``quadric_vertices`` off."""
    rng = np.random.default_rng(6)
    mesh = _dense(rng)
    params = GenerateParams(max_vertices=40, seed=1, temperature=1.0)
    off = pipe.generate(Shape(vertices=mesh.vertices, faces=mesh.faces), params)
    assert off.info["vertices_from"] == "decoder" and "quadric_fits" not in off.info
    monkeypatch.setattr(pipe, "triangle_config", replace(pipe.triangle_config, quadric_vertices=True))
    points, index = trimesh.sample.sample_surface(mesh, 2048, seed=0)
    cloud = pipe.generate(Shape(vertices=np.asarray(points), normals=np.asarray(mesh.face_normals[index])), params)
    assert cloud.info["vertices_from"] == "decoder" and "quadric_fits" not in cloud.info
