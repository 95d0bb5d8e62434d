"""Piecewise-planar inputs rebuilt from their planes (``fastmesh.shapes.planar``), on families drawn at random."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from fastmesh.evaluation.primitives import SHALLOW_KINDS, point_cloud, posed, random_shape
from fastmesh.params import GenerateParams
from fastmesh.pipeline import Pipeline
from fastmesh.shapes.io import with_normals
from fastmesh.shapes.orientation import oriented
from fastmesh.shapes.planar import PlanarConfig, planes_found, polyhedron
from fastmesh.shapes.shape import Normalization, Shape


def _rebuilt(mesh: Shape, seed: int, noise: float = 0.0):
    cloud = point_cloud(mesh, seed=seed)
    norm = Normalization.fit(cloud.vertices)
    pts = norm.apply(cloud.vertices)
    pts = pts + np.random.default_rng(seed).normal(0, noise, pts.shape)
    found = polyhedron(pts, cloud.normals)
    return norm, found


@pytest.mark.parametrize("kind", ["box", "l_block", "prism"])
def test_random_flat_shapes_come_back_as_their_own_corners_closed(kind):
    """Boxes, L blocks and prisms of random proportions, turned at random, half of them in millimetres far from
    the origin: as many vertices as the shape, each on one of its own, closed, oriented outward."""
    rng = np.random.default_rng(7)
    for i in range(5):
        mesh = posed(random_shape(kind, rng), rng, turn=True, millimetres=i % 2 == 1)
        norm, found = _rebuilt(mesh, seed=i)
        assert found is not None
        vertices, faces = found
        reference = norm.apply(mesh.vertices)
        assert len(vertices) == len(reference)
        nearest = np.linalg.norm(vertices[:, None] - reference[None], axis=-1).min(1)
        assert nearest.max() < 1e-4
        result = trimesh.Trimesh(vertices, faces, process=False)
        truth = trimesh.Trimesh(reference, mesh.faces, process=False)
        assert result.is_watertight and result.is_winding_consistent
        assert np.isclose(result.volume, abs(truth.volume), rtol=1e-3)  # positive: faces point outward


@pytest.mark.parametrize("kind", SHALLOW_KINDS)
def test_faces_a_few_degrees_from_flat_or_shut_still_meet(kind):
    """Low roofs whose slopes rise 1-5 degrees (faces 2-10 degrees from flat across the ridge) and wedges of 2-10
    degrees (faces that far from folding shut), any pose, from millimetres to kilometres: their own corners, closed,
    outward (planes meet down to ``arrangement.meeting_sine``; at 10 degrees none of these came back from the
    corners, only from the cells of their planes).  A wedge's back and a roof's eave wall are a few point spacings
    high: where the samples leave no points of two faces within a cover radius of each other at their short edge,
    that edge is not found, so 8 of 10 are asked for."""
    rng = np.random.default_rng(11)
    exact = 0
    for i in range(10):
        mesh = posed(random_shape(kind, rng), rng, turn=True, millimetres=i % 3 == 1)
        if i % 3 == 2:
            mesh = Shape(vertices=mesh.vertices * 1000.0, faces=mesh.faces)  # kilometres, as metres
        norm, found = _rebuilt(mesh, seed=i)
        if found is None:
            continue
        vertices, faces = found
        reference = norm.apply(mesh.vertices)
        result = trimesh.Trimesh(vertices, faces, process=False)
        assert result.is_watertight and result.is_winding_consistent
        assert np.isclose(result.volume, trimesh.Trimesh(reference, mesh.faces, process=False).volume, rtol=1e-3)
        nearest = np.linalg.norm(vertices[:, None] - reference[None], axis=-1).min(1)
        exact += len(vertices) == len(reference) and nearest.max() < 1e-4
    assert exact >= 8, exact


def _sheet_beside_a_box(rng: np.random.Generator) -> tuple[Shape, Shape]:
    """A rectangle (y = 0, facing up) and a box of random sides turned about two axes beside it, crossing the
    rectangle's plane a tenth of the size away from it."""
    w, d = rng.uniform(0.3, 0.6, 2)
    box = trimesh.creation.box(extents=rng.uniform(0.2, 0.4, 3))
    box.apply_transform(trimesh.transformations.rotation_matrix(rng.uniform(0.3, 1.2), [1, 0, 0])
                        @ trimesh.transformations.rotation_matrix(rng.uniform(0.3, 1.2), [0, 0, 1]))
    box.apply_translation([w + 0.1 + box.extents[0] / 2, 0, d / 2])
    sheet = np.array([[0, 0, 0], [w, 0, 0], [w, 0, d], [0, 0, d]], dtype=np.float64)
    return Shape(vertices=sheet, faces=np.array([[0, 2, 1], [0, 3, 2]])), Shape(vertices=box.vertices,
                                                                                  faces=box.faces)


def test_a_plane_takes_no_points_of_another_part_that_crosses_it():
    """A sheet with a turned box beside it whose faces cross the sheet's plane, in any pose: the points of the box's
    faces along that crossing lie on the plane within its tolerance, their normals at an angle to it, and are not
    the sheet's (a point on two planes goes to the one whose normal it shares).  The sheet's points come first, so
    its plane grows before the box's faces; before, 2-11 of the box's points on each of 8 went to the sheet, and its
    outline ran out to the box."""
    rng = np.random.default_rng(3)
    for i in range(8):
        sheet, box = _sheet_beside_a_box(rng)
        turn = trimesh.transformations.random_rotation_matrix(rng.random(3))[:3, :3]
        area = np.prod(np.ptp(sheet.vertices, 0)[[0, 2]])
        share = area / (area + trimesh.Trimesh(box.vertices, box.faces).area)
        parts = [point_cloud(part, n=int(8192 * f), seed=i) for part, f in ((sheet, share), (box, 1 - share))]
        points = np.vstack([c.vertices for c in parts]) @ turn.T * (1000.0 if i % 2 else 1.0)
        norm = Normalization.fit(points)
        found = planes_found(norm.apply(points), np.vstack([c.normals for c in parts]) @ turn.T, PlanarConfig())
        assert found is not None
        labels, mine = found[3], np.arange(len(points)) < len(parts[0].vertices)
        assert (labels[mine] == labels[0]).all() and (labels[~mine] != labels[0]).all(), i


def test_flat_shapes_without_normals_come_back_from_their_planes():
    """Points without normals, as a scanner's XYZ file: the normals estimated from neighbours (``io.with_normals``,
    then turned outward) tilt near every edge, yet the planes take the points that lie on them and the corners come
    back."""
    rng = np.random.default_rng(8)
    rebuilt = 0
    for i, kind in enumerate(["box", "l_block", "prism"] * 4):
        mesh = posed(random_shape(kind, rng), rng, turn=True, millimetres=i % 2 == 1)
        bare = oriented(with_normals(Shape(vertices=point_cloud(mesh, seed=i).vertices)))  # as Request.start
        norm = Normalization.fit(bare.vertices)
        found = polyhedron(norm.apply(bare.vertices), bare.normals)
        if found is not None:
            nearest = np.linalg.norm(found[0][:, None] - norm.apply(mesh.vertices)[None], axis=-1).min(1)
            rebuilt += len(found[0]) == len(mesh.vertices) and nearest.max() < 1e-3
    assert rebuilt >= 10, rebuilt


def test_a_faceted_cylinder_keeps_its_caps_as_polygons():
    """A 16-sided cylinder: 18 planes; the caps' outlines have 16 corners, no sliver of the arrangement's
    crossing lines beyond them."""
    rng = np.random.default_rng(3)
    mesh = posed(random_shape("cylinder", rng), rng)
    _, found = _rebuilt(mesh, seed=1)
    assert found is not None and len(found[0]) == 32
    assert trimesh.Trimesh(*found, process=False).is_watertight


def test_curved_inputs_are_not_polyhedra_and_noisy_flat_ones_are():
    """A sphere gives None (the networks decide); a box's points moved off their planes by noise of 0.2 % of its
    size still give its 12 triangles, held by planes at the noise read from the points (``noise.noise_level``)."""
    sphere = trimesh.creation.icosphere(subdivisions=4)
    assert _rebuilt(Shape(vertices=sphere.vertices, faces=sphere.faces), seed=0)[1] is None
    box = random_shape("box", np.random.default_rng(0))
    assert _rebuilt(box, seed=0)[1] is not None
    norm, noisy = _rebuilt(box, seed=0, noise=2e-3)
    assert noisy is not None and len(noisy[1]) == 12
    assert np.linalg.norm(noisy[0][:, None] - norm.apply(box.vertices)[None], axis=-1).min(1).max() < 3e-3


def test_the_pipeline_rebuilds_a_dense_flat_mesh_unless_asked_otherwise():
    """A subdivided, turned box (192 faces, no low-poly input): its 8 corners from the planes, no tokens decoded;
    with a face-count target the rebuild split to it, closed, every vertex on the box; closed=false leaves it to
    the networks."""
    pipe = Pipeline.random("tiny", seed=0)
    box = trimesh.creation.box(extents=(3.0, 2.0, 1.0)).subdivide().subdivide()
    box.apply_transform(trimesh.transformations.rotation_matrix(0.6, [1.0, 2.0, 3.0]))
    shape = Shape(vertices=np.asarray(box.vertices), faces=np.asarray(box.faces))
    res = pipe.generate(shape, GenerateParams(seed=0, max_vertices=24))
    assert res.info["result_from"] == "planes" and res.tokens == 0
    assert len(res.vertices) == 8 and len(res.faces) == 12 and res.quality["watertight"]
    corners = np.asarray(trimesh.creation.box(extents=(3.0, 2.0, 1.0)).vertices)
    corners = trimesh.transform_points(corners, trimesh.transformations.rotation_matrix(0.6, [1.0, 2.0, 3.0]))
    assert np.linalg.norm(res.vertices[:, None] - corners[None], axis=-1).min(1).max() < 1e-3
    asked = pipe.generate(shape, GenerateParams(seed=0, max_vertices=24, target_faces=40))
    assert asked.info["result_from"] == "planes" and asked.tokens == 0 and asked.quality["count_step"] == "split"
    assert asked.quality["target_met"] and asked.quality["watertight"] and len(asked.faces) >= 40
    assert np.isclose(trimesh.Trimesh(asked.vertices, asked.faces, process=False).area, box.area)
    own = trimesh.transform_points(asked.vertices, np.linalg.inv(trimesh.transformations.rotation_matrix(
        0.6, [1.0, 2.0, 3.0])))  # back in the box's frame: every vertex on a side
    assert np.abs(np.abs(own) - np.array([1.5, 1.0, 0.5])).min(1).max() < 1e-6
    assert pipe.generate(shape, GenerateParams(seed=0, max_vertices=24, closed="false")).info["result_from"] != "planes"
