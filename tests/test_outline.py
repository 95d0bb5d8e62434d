"""Flat regions triangulated from their outlines (``faces.outline``), and the pipeline's weighing of that
(``pipeline.finish.outlined_flat``): random families of flat-sided shapes in any pose and unit, each cut into many
faces with its vertices a little off its planes, against the shapes themselves."""

from __future__ import annotations

from dataclasses import replace

import manifold3d
import numpy as np
import pytest
import torch
import trimesh
from poses import posed, random_pose

from fastmesh.evaluation.quality import topology
from fastmesh.faces.meshops import distance_to_triangles, wound_alike
from fastmesh.faces.outline import OutlineConfig, outlined, regions_within
from fastmesh.params import GenerateParams
from fastmesh.pipeline import Pipeline, finish
from fastmesh.shapes.shape import Shape

torch.set_num_threads(1)
TOL = OutlineConfig().tol


def _dense(mesh: trimesh.Trimesh, rng: np.random.Generator, pose: tuple, splits: int = 2
           ) -> tuple[np.ndarray, np.ndarray]:
    """``mesh`` cut into many faces (its longest edges split ``splits`` times over), posed, each vertex moved off
    its place by a twentieth of the tolerance at most (a decoder's vertices are never exactly on their planes)."""
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    for _ in range(splits):
        v, f = trimesh.remesh.subdivide(v, f)
    size = float(np.ptp(v, axis=0).max())
    v = v + rng.uniform(-1, 1, v.shape) * TOL * size / 20
    return posed(v, pose), f


def _box(rng: np.random.Generator, lo: int = 4, hi: int = 20) -> manifold3d.Manifold:
    """A box from the origin, its sides of ``lo`` to ``hi`` whole steps."""
    return manifold3d.Manifold.cube(tuple(float(x) for x in rng.integers(lo, hi + 1, 3)))


def _kitbashed(rng: np.random.Generator) -> trimesh.Trimesh:
    """A flat-sided prop of 2-4 boxes that overlap (insets, steps, bays), as their union.  Sides and offsets are
    whole steps of 0.05, as a modeller snaps them: parts flush with each other or offset by at least 0.05, several
    tolerances (the boolean runs in whole steps, which its float32 holds exactly, and is scaled after)."""
    solid = _box(rng)
    for _ in range(rng.integers(1, 4)):
        solid = solid + _box(rng).translate(tuple(float(x) for x in rng.integers(-8, 9, 3)))
    if rng.random() < 0.5:  # a bay cut into it
        solid = solid - _box(rng, 2, 10).translate(tuple(float(x) for x in rng.integers(-6, 13, 3)))
    out = solid.to_mesh()  # parts that share an edge meet there at two copies of each vertex: made one
    return trimesh.Trimesh(np.asarray(out.vert_properties)[:, :3] * 0.05, np.asarray(out.tri_verts))


def _farthest(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> float:
    """How far the vertices of each mesh lie from the other's surface, at most."""
    return float(max(distance_to_triangles(a[0], *b).max(), distance_to_triangles(b[0], *a).max()))


@pytest.mark.parametrize("seed", range(6))
def test_a_dense_box_comes_back_as_its_twelve_faces(seed):
    """A box of any proportions, pose and unit, cut into hundreds of faces with its vertices off its planes,
    comes back as 8 vertices and 12 faces, closed, wound as it was (outward), within two tolerances of itself."""
    rng = np.random.default_rng(seed)
    box = trimesh.creation.box(rng.uniform(0.2, 1.0, 3))
    v, f = _dense(box, rng, random_pose(rng), splits=int(rng.integers(1, 4)))
    out_v, out_f, removed = outlined(v, f)
    assert (len(out_v), len(out_f)) == (8, 12) and removed == len(v) - 8
    assert topology(out_f)["watertight"] and wound_alike(out_f)
    assert trimesh.Trimesh(out_v, out_f, process=False).volume > 0
    assert _farthest((v, f), (out_v, out_f)) <= 2 * TOL * np.ptp(v, axis=0).max()


@pytest.mark.parametrize("seed", range(8))
def test_a_kitbashed_prop_keeps_its_insets_and_steps_with_no_more_faces_than_its_union(seed):
    """A union of overlapping boxes, with or without a bay cut into it (insets, steps, bays), cut into many faces
    and posed: its flat sides come back from their outlines, with no more faces than the union itself has (as
    ``manifold3d`` makes it), closed and wound alike, within two tolerances of the union, its volume within 5 %."""
    rng = np.random.default_rng(100 + seed)
    union = _kitbashed(rng)
    pose = random_pose(rng)
    v, f = _dense(union, rng, pose, splits=2)
    out_v, out_f, _ = outlined(v, f)
    turn, scale, shift = pose
    exact = (np.asarray(union.vertices) @ turn.T * scale + shift, np.asarray(union.faces))
    assert len(out_f) <= len(union.faces) < len(f)
    assert topology(out_f)["watertight"] and wound_alike(out_f)
    assert _farthest(exact, (out_v, out_f)) <= 2 * TOL * np.ptp(v, axis=0).max()
    assert np.isclose(trimesh.Trimesh(out_v, out_f).volume, union.volume * scale**3, rtol=0.05)


@pytest.mark.parametrize("seed", range(4))
def test_a_round_part_keeps_its_facets_and_meets_the_flat_part_without_a_gap(seed):
    """A box with a round boss on top (a mixed shape), cut into many faces: every vertex of the shape itself stays
    (the boss's 16-40 facets, each flat, turn by 9-22 degrees, more than the tolerance allows over their width),
    the extra vertices of the dense copy go, and flat and round parts still meet edge to edge (closed, wound
    alike), with no more faces than the shape."""
    rng = np.random.default_rng(200 + seed)
    boss = manifold3d.Manifold.cylinder(0.6, 0.25, circular_segments=int(rng.integers(16, 41)))
    out = (manifold3d.Manifold.cube((1.0, 1.0, 0.4), center=True) + boss.translate((0.0, 0.0, 0.2))).to_mesh()
    mesh = trimesh.Trimesh(np.asarray(out.vert_properties)[:, :3], np.asarray(out.tri_verts))
    v, f = _dense(mesh, rng, random_pose(rng), splits=1)  # the shape's own vertices first, then the edges' midpoints
    out_v, out_f, removed = outlined(v, f)
    assert {tuple(x) for x in out_v} == {tuple(x) for x in v[:len(mesh.vertices)]}
    assert removed == len(v) - len(mesh.vertices) and len(out_f) <= len(mesh.faces)
    assert topology(out_f)["watertight"] and wound_alike(out_f)


def test_an_open_sheet_keeps_its_border_and_a_sphere_its_shape():
    """A flat square sheet cut into a grid comes back as two faces with its four open edges; a sphere, curved
    everywhere, stays within two tolerances of itself, closed."""
    rng = np.random.default_rng(7)
    grid = trimesh.creation.box((1.0, 1.0, 1.0))
    top = grid.faces[grid.face_normals[:, 2] > 0.5]
    sheet = trimesh.Trimesh(grid.vertices, top)
    v, f = _dense(sheet, rng, random_pose(rng), splits=3)
    out_v, out_f, _ = outlined(v, f)
    assert len(out_f) == 2 and topology(out_f)["boundary_edges"] == 4
    sphere = trimesh.creation.icosphere(3)
    v, f = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    out_v, out_f, _ = outlined(v, f)
    assert topology(out_f)["watertight"] and wound_alike(out_f)
    assert _farthest((v, f), (out_v, out_f)) <= 2 * TOL * 2.0


def test_regions_do_not_cross_a_crease_or_a_fold():
    """The faces of a box fall into its six sides; a sheet folded back onto itself (two faces wound against each
    other across an edge) is two regions, not one."""
    box = trimesh.creation.box((1.0, 2.0, 3.0))
    v, f = trimesh.remesh.subdivide(box.vertices, box.faces)
    labels, normals = regions_within(v, f, 10.0, 1e-6)
    assert len(normals) == 6 and len(np.unique(labels)) == 6
    folded = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], dtype=float)
    labels, _ = regions_within(folded, np.array([[0, 1, 2], [1, 2, 3]]), 10.0, 1e-6)
    assert labels[0] != labels[1]


def test_the_pipeline_weighs_the_outlined_result_and_reports_it(monkeypatch):
    """With ``TriangleConfig.outline`` a result is weighed against its outlined self: ``info`` holds both fits and
    the vertices removed; a rival that lies farther (here blown up by half) does not come back and removes none;
    one as near comes back."""
    pipe = Pipeline.random(seed=0)
    assert not pipe.triangle_config.outline
    monkeypatch.setattr(pipe, "triangle_config", replace(pipe.triangle_config, outline=True))
    seen = []
    monkeypatch.setattr(finish, "outlined", lambda v, f: seen.append(len(f)) or (v * 1.5, f, 3))
    sphere = trimesh.creation.icosphere(3)
    points, normals = sphere.sample(2048, return_index=True)
    normals = sphere.face_normals[normals]
    shape = Shape(vertices=np.asarray(points), normals=np.asarray(normals))
    res = pipe.generate(shape, GenerateParams(max_vertices=48, seed=1))
    fits = res.info["outline_fits"]
    assert seen and fits["model"] * finish.FEWER_FACES_MARGIN < fits["outlined"]
    assert res.info["flat_vertices_removed"] == 0 and len(res.faces) == seen[0]
    # A rival as near (the result's faces listed the other way round; the result less a face would have a hole the
    # weighing counts): it comes back, its removed vertices reported.
    monkeypatch.setattr(finish, "outlined", lambda v, f: (v, f[::-1], 3))
    kept = pipe.generate(shape, GenerateParams(max_vertices=48, seed=1))
    fits = kept.info["outline_fits"]
    assert kept.info["flat_vertices_removed"] == 3 and fits["outlined"] <= fits["model"] * finish.FEWER_FACES_MARGIN


def _square_with_centre(turn: int) -> tuple[np.ndarray, np.ndarray]:
    """A flat square A B C D fanned around its centre O (four faces, wound up), its corners named from ``turn``."""
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 0]], dtype=float)
    ring = np.roll(np.arange(4), turn)
    return v, np.array([[ring[k], ring[(k + 1) % 4], 4] for k in range(4)])


@pytest.mark.parametrize("turn", range(4))
def test_a_region_keeps_the_surface_manifold_and_free_of_crossings(turn):
    """A square fanned around its centre, with a sheet below hanging from one of its diagonals (the edge A-C in one
    more face): cut from its outline, the square must not take that diagonal (an edge of three faces), whichever
    corner its outline starts from; with a spike through it instead, it keeps its faces (a new face would cross)."""
    v, f = _square_with_centre(turn)
    v = np.r_[v, [[0.5, 0.5, -1.0]]]
    sheet = np.r_[f, [[2, 0, 5]]]  # A-C as a side of a face below the square
    out_v, out_f, _ = outlined(v, sheet)
    assert max(np.unique(np.sort(out_f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0,
                         return_counts=True)[1]) <= 2
    spike = np.r_[v, [[0.3, 0.7, 0.5], [0.35, 0.65, -0.5], [0.3, 0.6, -0.5]]]
    pierced = np.r_[f, [[6, 7, 8]]]
    out_v, out_f, removed = outlined(spike, pierced)
    assert removed == 0 and len(out_f) == len(pierced)
