"""A generated result's vertices its shape does not need, collapsed (``pipeline.finish.coarsened``).

The random family: boxes, cylinders of 24-48 sides and ellipsoids of any proportions, pose and unit (millimetres to
kilometres), cut finer than their shape (each face split in four, once or twice) and shaken by a twentieth of a
cell, as a decoder's vertices on a flat or gently curved side are.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import trimesh
from poses import posed, random_pose
from test_visible import _moebius

import fastmesh.pipeline as pipeline_module
from fastmesh.evaluation.quality import topology
from fastmesh.faces.crossings import crossing_faces
from fastmesh.faces.facecount import decimate
from fastmesh.faces.meshops import distance_to_triangles, wound_alike
from fastmesh.faces.triangles import TriangleConfig
from fastmesh.params import GenerateParams
from fastmesh.pipeline import Pipeline, finish
from fastmesh.request import Request
from fastmesh.shapes.shape import Shape
from fastmesh.tokenizer.grid import CELL

MOVE = TriangleConfig().coarsen
DATA = Path(__file__).parent / "data"


def _posed(mesh: trimesh.Trimesh, rng: np.random.Generator) -> trimesh.Trimesh:
    """``mesh`` scaled to a unit from millimetres to kilometres, turned and moved at random."""
    scale = 10.0 ** rng.uniform(-3, 3)
    turn = trimesh.transformations.random_rotation_matrix(rng.random(3))
    out = mesh.copy()
    out.apply_transform(turn)
    out.apply_scale(scale)
    out.apply_translation(rng.uniform(-2, 2, 3) * scale)
    return out


def _shape(rng: np.random.Generator, kind: str) -> trimesh.Trimesh:
    sides = rng.uniform(0.3, 1.0, 3)
    if kind == "box":
        return trimesh.creation.box(sides)
    if kind == "cylinder":
        return trimesh.creation.cylinder(sides[0] / 2, sides[1], sections=int(rng.integers(24, 49)))
    sphere = trimesh.creation.icosphere(3)
    sphere.apply_scale(sides / 2)
    return sphere


def _finer(mesh: trimesh.Trimesh, rng: np.random.Generator, splits: int) -> tuple[np.ndarray, np.ndarray]:
    """``mesh`` with each face split in four ``splits`` times, its vertices shaken by a twentieth of a cell of its
    longest side."""
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    for _ in range(splits):
        v, f = trimesh.remesh.subdivide(v, f)
    size = float(np.ptp(v, axis=0).max())
    return v + rng.normal(0.0, 0.05 * CELL * size / np.sqrt(3), v.shape), f


def _own_samples(vertices: np.ndarray, faces: np.ndarray, n: int = 4096) -> np.ndarray:
    """(n, 3) samples of the mesh itself: its input, where the mesh is what the input was read as."""
    return np.asarray(trimesh.Trimesh(vertices, faces, process=False).sample(n, seed=0))


def _request(mesh: trimesh.Trimesh) -> Request:
    points, index = mesh.sample(4096, return_index=True, seed=0)
    return Request.start(Shape(vertices=np.asarray(points), normals=np.asarray(mesh.face_normals[index])),
                         GenerateParams())


@pytest.mark.parametrize("kind", ["box", "cylinder", "ellipsoid"])
def test_a_shape_cut_finer_than_it_needs_comes_back_with_fewer_faces_near_itself(kind):
    """Each of 3 random poses: at most a third of the faces come back (boxes: at most 2 per side, their flat
    sides), closed, wound alike, crossing nothing, within a cell of the true surface both ways."""
    rng = np.random.default_rng({"box": 1, "cylinder": 2, "ellipsoid": 3}[kind])
    for _ in range(3):
        true = _posed(_shape(rng, kind), rng)
        v, f = _finer(true, rng, splits=1 if kind == "ellipsoid" else 2)
        rival, fits, removed = finish.coarsened(_request(true), v, f, MOVE, 4096)
        assert rival is not None, fits
        out_v, out_f = rival
        assert removed == len(f) - len(out_f) and len(out_f) <= len(f) / 3, (len(f), len(out_f))
        if kind == "box":
            assert len(out_f) <= 24, len(out_f)
        t = topology(out_f)
        assert t["watertight"] and t["pieces"] == 1 and wound_alike(out_f)
        assert not crossing_faces(out_v, out_f).any()
        size = float(np.ptp(true.vertices, axis=0).max())
        assert fits["coarsened"] <= finish.FEWER_FACES_MARGIN * fits["model"]
        far = max(distance_to_triangles(out_v, np.asarray(true.vertices), np.asarray(true.faces)).max(),
                  distance_to_triangles(np.asarray(true.vertices), out_v, out_f).max())
        assert far <= CELL * size, far / size
        # The vertices on the sides of the box stay: the box is the input's.
        assert np.allclose(out_v.min(0), v.min(0)) and np.allclose(out_v.max(0), v.max(0))


def test_a_collapse_that_would_open_or_cross_the_surface_is_refused(monkeypatch):
    """Collapses that leave an open edge or fold one face through another never come back, whatever their fit."""
    rng = np.random.default_rng(4)
    true = _posed(trimesh.creation.box(rng.uniform(0.3, 1.0, 3)), rng)
    v, f = _finer(true, rng, splits=2)
    req = _request(true)
    monkeypatch.setattr(finish, "decimate", lambda v, f, target, **k: f[1:])  # a hole
    assert finish.coarsened(req, v, f, MOVE, 4096) == (None, {}, 0)
    # A face moved through the box's middle: its corners are three far-apart vertices of the box.
    far = np.array([[0, int(np.argmax(np.linalg.norm(v - v[0], axis=1))), len(v) // 2]])
    monkeypatch.setattr(finish, "decimate", lambda v, f, target, **k: np.concatenate([f, far, far[:, ::-1]]))
    assert finish.coarsened(req, v, f, MOVE, 4096) == (None, {}, 0)


@pytest.mark.parametrize("seed", range(3))
def test_a_defect_apart_from_the_collapses_does_not_weigh_them_farther(seed):
    """A box cut finer than it needs beside a small twisted band (a Moebius strip: two faces along its twist no
    turning makes agree), together at any pose and unit: the box's collapses come back, though the band's faces are
    then a larger share of the faces; the defect is weighed by its share of the area, which they leave as it was."""
    rng = np.random.default_rng(seed)
    box = trimesh.creation.box(rng.uniform(0.3, 1.0, 3))
    v, f = _finer(box, rng, splits=2)
    band_v, band_f = _moebius(12, range(0))
    band_v = band_v * 0.15 + [1.2, 0.0, 0.0]
    pose = random_pose(rng)
    true = trimesh.Trimesh(posed(np.r_[box.vertices, band_v], pose), np.r_[box.faces, band_f + len(box.vertices)],
                           process=False)
    both_v, both_f = posed(np.r_[v, band_v], pose), np.r_[f, band_f + len(v)]
    rival, fits, removed = finish.coarsened(_request(true), both_v, both_f, MOVE, 4096)
    assert rival is not None, fits
    assert len(rival[1]) <= 24 + len(band_f) < len(both_f) / 4, len(rival[1])
    assert fits["coarsened"] <= finish.FEWER_FACES_MARGIN * fits["model"]


def test_collapses_that_fold_a_wing_through_another_part_are_made_again_around_it():
    """A decoded Cessna (``data/folding_collapses.npz``: crossing nothing) folds through itself under plain
    collapses; the rounds keep the vertices around the folds and give back a mesh that crosses nothing, with most of
    the collapses still made."""
    with np.load(DATA / "folding_collapses.npz") as d:
        v, f = d["vertices"].astype(np.float64), d["faces"].astype(np.int64)
    assert not crossing_faces(v, f).any()
    plain = decimate(v, f, 0, max_move=MOVE)
    assert crossing_faces(v, plain).any()
    fewer = finish._collapsed(v, f, MOVE, np.zeros((0, 3)))  # the rounds around folds alone
    assert fewer is not None and not crossing_faces(v, fewer).any()
    assert len(fewer) < len(f) - (len(f) - len(plain)) / 2, (len(f), len(plain), len(fewer))
    # Read against its input (here its own samples), the rounds keep more: no sample is left a cell farther.
    points = _own_samples(v, f)
    near = finish._collapsed(v, f, MOVE, points)
    assert near is not None and not crossing_faces(v, near).any() and len(fewer) <= len(near) < len(f)
    assert (distance_to_triangles(points, v, near) <= distance_to_triangles(points, v, f) + finish.LEFT_TOL).all()


def _spiky(rng: np.random.Generator) -> trimesh.Trimesh:
    """A ball with three thin spikes (radius 0.01-0.02 of their length's 0.25-0.35, six-sided) pointing away from
    its axes, so that their tips are no sides of its box."""
    parts = [trimesh.creation.icosphere(3, radius=0.5)]
    while len(parts) < 4:
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        if np.abs(d).max() >= 0.75:
            continue
        cone = trimesh.creation.cone(rng.uniform(0.01, 0.02), rng.uniform(0.25, 0.35), sections=6)
        cone.apply_translation((0.0, 0.0, 0.3))
        turn = trimesh.transformations.rotation_matrix(np.arccos(d[2]), np.cross((0.0, 0.0, 1.0), d))
        parts.append(cone.apply_transform(turn))
    return trimesh.boolean.union(parts, engine="manifold")


def test_collapses_never_cut_a_thin_spike_short():
    """A thin spike's faces weigh little in a collapse's quadric: plain collapses within a quarter cell of their
    planes cut spikes short by up to 16 cells.  The rounds keep the vertices where an input sample would end more
    than ``LEFT_TOL`` farther: on 6 random spiky balls, any pose and unit, cut finer than they need, no sample
    does, for a few more faces than the plain collapses leave."""
    from fastmesh.shapes.shape import Normalization

    rng = np.random.default_rng(7)
    cut_short = 0
    for _ in range(6):
        true = _posed(_spiky(rng), rng)
        v, f = trimesh.remesh.subdivide_to_size(true.vertices, true.faces, 0.05 * float(np.ptp(true.vertices, 0).max()))
        norm = Normalization.fit(v)
        unit, points = norm.apply(v), norm.apply(np.asarray(true.sample(16384, seed=0)))
        plain = decimate(unit, f, 0, max_move=MOVE)
        cut_short += bool(finish._left(unit, f, plain, points).any())
        fewer = finish._collapsed(unit, f, MOVE, points)
        assert fewer is not None and len(fewer) <= 1.05 * len(plain), (len(plain), len(fewer))
        assert not finish._left(unit, f, fewer, points).any()
    assert cut_short >= 2  # the family has spikes the plain collapses cut short


def test_the_pipeline_coarsens_a_result_only_without_a_face_count(monkeypatch):
    """With ``TriangleConfig.coarsen`` a generated result, once closed, is weighed against its collapsed self:
    ``info`` holds the faces removed (0 where the rival is refused) and, where weighed, both fits; a ``target_faces``
    brings the result to its count instead and nothing is collapsed."""
    pipe = Pipeline.random(seed=0)
    assert pipe.triangle_config.coarsen is None and MOVE == 0.25 * CELL
    monkeypatch.setattr(pipe, "triangle_config", replace(pipe.triangle_config, coarsen=MOVE))
    seen, order = [], []
    real = finish.decimate
    monkeypatch.setattr(finish, "decimate", lambda *a, **k: seen.append(len(a[1])) or real(*a, **k))
    # After the closing: it fills a hole from the faces around it, which the collapses would have made coarser.
    closing = pipeline_module.closed_result
    monkeypatch.setattr(pipeline_module, "closed_result", lambda *a, **k: order.append("closed") or closing(*a, **k))
    coarsen = finish.coarsened
    monkeypatch.setattr(finish, "coarsened", lambda *a, **k: order.append("coarsened") or coarsen(*a, **k))
    sphere = trimesh.creation.icosphere(3)
    points, index = sphere.sample(2048, return_index=True, seed=0)
    shape = Shape(vertices=np.asarray(points), normals=np.asarray(sphere.face_normals[index]))
    res = pipe.generate(shape, GenerateParams(max_vertices=48, seed=1))
    assert seen and "faces_coarsened" in res.info and order == ["closed", "coarsened"]
    fits = res.info.get("coarsen_fits")
    if res.info["faces_coarsened"]:
        assert fits["coarsened"] <= finish.FEWER_FACES_MARGIN * fits["model"]
    seen.clear()
    told = pipe.generate(shape, GenerateParams(max_vertices=48, seed=1, target_faces=40))
    assert not seen and "faces_coarsened" not in told.info
