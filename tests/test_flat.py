"""A dense mesh made of flat faces simplified within its own surface (``fastmesh.faces.flat``), and the pipeline
giving it back without running the networks."""

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from fastmesh.evaluation.primitives import posed, random_shape
from fastmesh.evaluation.quality import topology
from fastmesh.faces import flat
from fastmesh.faces.facecount import decimate
from fastmesh.faces.meshops import edge_face_counts, piece_labels, remove_unreferenced
from fastmesh.models.generate import Cancelled
from fastmesh.params import GenerateParams
from fastmesh.shapes.shape import Normalization, Shape
from fastmesh.tokenizer.grid import CELL


def _dense(shape: Shape, rng: np.random.Generator, size: float = 0.06) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``shape`` turned at random into the unit cube and split into faces under ``size``; its own vertices too."""
    turned = posed(shape, rng)
    unit = Normalization.fit(turned.vertices).apply(turned.vertices)
    v, f = trimesh.remesh.subdivide_to_size(unit, turned.faces, size)
    return v, f, unit


def _grid(a: np.ndarray, b: np.ndarray, point) -> tuple[np.ndarray, np.ndarray]:
    """A flat sheet of triangles over the grid ``a`` x ``b``; ``point(x, y)`` places a grid point in 3D."""
    x, y = np.meshgrid(a, b, indexing="ij")
    v = np.stack(point(x.ravel(), y.ravel()), axis=1)
    n = len(b)
    i = np.arange(len(a) * n).reshape(len(a), n)[:-1, :-1].ravel()
    return v, np.r_[np.c_[i, i + n, i + 1], np.c_[i + 1, i + n, i + n + 1]]


def _lidless(rng: np.random.Generator) -> trimesh.Trimesh:
    """A box of extents drawn at random without its top face's two triangles."""
    box = trimesh.creation.box(extents=rng.uniform(0.3, 1.0, 3))
    return box.submesh([np.flatnonzero(box.face_normals[:, 2] < 0.5)], append=True)


@pytest.mark.parametrize("kind", ["box", "l_block", "prism"])
def test_flat_shapes_of_any_proportions_and_pose_come_back_as_their_own_corners(kind):
    rng = np.random.default_rng({"box": 1, "l_block": 2, "prism": 3}[kind])
    for _ in range(2):
        v, f, own = _dense(random_shape(kind, rng), rng)
        out_v, out_f = flat.simplify_flat(v, f)
        assert len(out_v) == len(own)
        assert cKDTree(own).query(out_v)[0].max() < 1e-9 and cKDTree(out_v).query(own)[0].max() < 1e-9
        assert topology(out_f)["watertight"]


def test_an_open_mesh_in_two_pieces_keeps_its_opening_and_its_pieces():
    rng = np.random.default_rng(4)
    lidless = _lidless(rng)
    other = trimesh.creation.box(extents=(0.2, 0.3, 0.1))
    other.apply_translation((1.5, 0.0, 0.0))
    both = trimesh.util.concatenate([lidless, other])
    unit = Normalization.fit(both.vertices).apply(both.vertices)
    mesh = trimesh.Trimesh(*trimesh.remesh.subdivide_to_size(unit, both.faces, 0.04))
    mesh.merge_vertices()
    out_v, out_f = flat.simplify_flat(np.asarray(mesh.vertices), np.asarray(mesh.faces))
    assert len(out_v) == 16 and len(out_f) == 10 + 12  # the lidless box's 8 corners and 10 faces, the box's
    assert topology(out_f)["boundary_edges"] == 4 and len(np.unique(piece_labels(out_f))) == 2


def test_a_curved_mesh_is_left_to_the_networks():
    sphere = trimesh.creation.icosphere(4)
    assert flat.flat_share(sphere.vertices, sphere.faces, 0.5) < 0.1
    assert flat.simplify_flat(np.asarray(sphere.vertices), np.asarray(sphere.faces)) is None


def test_collapses_stay_within_the_bound_and_the_gap_sees_a_stray_vertex():
    # A flat square grid with one vertex raised by half a cell: the bound keeps the bump, no bound flattens it.
    n = 12
    v, f = _grid(np.linspace(0, 1, n), np.linspace(0, 1, n), lambda x, y: (x, y, 0 * x))
    bump = (n // 2) * n + n // 2
    v[bump, 2] = 0.5 * CELL
    kept = remove_unreferenced(v, decimate(v, f, 1, max_move=0.1 * CELL))[0]
    assert np.isclose(kept[:, 2].max(), 0.5 * CELL)
    flattened = remove_unreferenced(v, decimate(v, f, 1))[0]
    assert flattened[:, 2].max() == 0.0
    moved = v.copy()
    moved[bump, 2] = 2.5 * CELL
    assert 1.9 * CELL < flat._gap(v, f, moved, f) <= 2.0 * CELL  # the bump is half a cell high
    assert flat._gap(v, f, v, f) < 1e-6 * CELL  # the input samples are float32


def test_the_pipeline_gives_a_flat_mesh_back_simplified_at_the_count_asked_unless_closing_is_asked():
    from fastmesh.pipeline import Pipeline

    rng = np.random.default_rng(6)
    lidless = _lidless(rng)
    mesh = trimesh.Trimesh(*trimesh.remesh.subdivide_to_size(lidless.vertices * 250.0 + 1e4, lidless.faces, 10.0))
    mesh.merge_vertices()
    shape = Shape(vertices=np.asarray(mesh.vertices), faces=np.asarray(mesh.faces))
    pipe = Pipeline.random()
    res = pipe.generate(shape, GenerateParams(seed=0, max_vertices=48))
    assert res.info["result_from"] == "simplified" and res.tokens == 0 and len(res.faces) == 10
    assert cKDTree(lidless.vertices * 250.0 + 1e4).query(res.vertices)[0].max() < 1e-6
    assert res.quality["boundary_edges"] == 4
    asked = pipe.generate(shape, GenerateParams(seed=0, max_vertices=48, target_faces=40))
    assert asked.info["result_from"] == "simplified" and asked.quality["count_step"] == "split"
    assert asked.quality["target_met"] and len(asked.faces) >= 40 and asked.quality["boundary_edges"] >= 4
    tris = lidless.vertices[lidless.faces] * 250.0 + 1e4  # the input's surface, as its few flat faces
    at = np.tile(asked.vertices, (len(tris), 1))
    near = trimesh.triangles.closest_point(np.repeat(tris, len(asked.vertices), 0), at)
    gap = np.linalg.norm(near - at, axis=1).reshape(len(tris), -1).min(0)
    assert gap.max() < 1e-6  # every vertex on the input's surface
    assert np.isclose(trimesh.Trimesh(asked.vertices, asked.faces, process=False).area, mesh.area)
    closed = pipe.generate(shape, GenerateParams(seed=0, max_vertices=48, closed="true"))
    assert closed.info["result_from"] != "simplified"
    with pytest.raises(Cancelled):  # a cancel asked while it simplifies stops the job, not a result
        pipe.generate(shape, GenerateParams(seed=0, max_vertices=48), should_cancel=lambda: True)


def test_a_mesh_split_at_every_face_like_an_stl_is_welded_first():
    rng = np.random.default_rng(7)
    v, f, own = _dense(random_shape("l_block", rng), rng, size=0.1)
    split_v, split_f = v[f].reshape(-1, 3), np.arange(3 * len(f)).reshape(-1, 3)
    out_v, out_f = flat.simplify_flat(split_v, split_f)
    assert len(out_v) == len(own) and cKDTree(own).query(out_v)[0].max() < 1e-9
    assert topology(out_f)["watertight"]


def test_a_mesh_with_an_edge_in_three_faces_is_left_to_the_networks():
    """A fin standing on a plate along a line of the plate's edges: flat everywhere, but those edges have three
    faces each, and a result must be edge-manifold."""
    a = np.linspace(-1.0, 1.0, 21)
    plate_v, plate_f = _grid(a, a, lambda x, y: (x, y, 0 * x))
    fin_v, fin_f = _grid(a, np.linspace(0.0, 1.0, 11), lambda x, z: (x, 0 * x, z))
    mesh = trimesh.Trimesh(np.vstack([plate_v, fin_v]), np.vstack([plate_f, fin_f + len(plate_v)]), process=False)
    mesh.merge_vertices()
    assert edge_face_counts(mesh.faces).max() == 3
    assert flat.flat_share(mesh.vertices, mesh.faces, 0.5) > 0.9
    assert flat.simplify_flat(np.asarray(mesh.vertices), np.asarray(mesh.faces)) is None
    plate = flat.simplify_flat(plate_v, plate_f)  # the plate alone is simplified
    assert plate is not None and len(plate[1]) == 2
