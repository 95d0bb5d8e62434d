"""Whole results (fastmesh.faces.pieces): pinched vertices split per fan, stray pieces dropped."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import trimesh

from fastmesh.evaluation.quality import topology
from fastmesh.faces.pieces import drop_strays, split_pinches


def _boxes(offsets, sizes=None) -> trimesh.Trimesh:
    parts = []
    for i, o in enumerate(offsets):
        b = trimesh.creation.box(extents=np.full(3, 1.0 if sizes is None else sizes[i]))
        b.apply_translation(o)
        parts.append(b)
    m = trimesh.util.concatenate(parts)
    m.merge_vertices()
    return m


def test_boxes_touching_at_corners_are_split_into_manifold_pieces():
    rng = np.random.default_rng(0)
    for _ in range(5):
        # A chain of boxes, each touching the last at one corner: every shared corner is pinched.
        k = int(rng.integers(2, 5))
        m = _boxes([[i, i, i] for i in range(k)])
        assert topology(m.faces)["non_manifold_vertices"] == k - 1
        v, f = split_pinches(m.vertices, m.faces)
        top = topology(f)
        assert top["non_manifold_vertices"] == 0 and top["watertight"] and top["pieces"] == k
        assert len(v) == len(m.vertices) + k - 1
        assert np.array_equal(v[f], np.asarray(m.vertices)[m.faces])  # no corner moved


def test_a_manifold_mesh_is_left_as_it_is():
    m = trimesh.creation.icosphere(2)
    v, f = split_pinches(m.vertices, m.faces)
    assert np.array_equal(v, m.vertices) and np.array_equal(f, m.faces)


def test_strays_go_smallest_first_down_to_the_inputs_pieces():
    m = _boxes([[0, 0, 0], [5, 0, 0], [0, 5, 0], [0, 0, 5]], sizes=[2.0, 1.0, 0.03, 0.04])
    f = np.asarray(m.faces)
    # Two small boxes (under half a percent of the area each) beside two big ones.
    assert topology(drop_strays(m.vertices, f, keep=4))["pieces"] == 4
    three = drop_strays(m.vertices, f, keep=3)
    assert topology(three)["pieces"] == 3 and len(three) == 36  # the smallest went
    assert topology(drop_strays(m.vertices, f, keep=1))["pieces"] == 2  # the unit box is no stray
    sliver = np.array([[0, 1, 2], [0, 2, 1]])  # a triangle closed with its own back: two faces
    long = np.array([[10.0, 0, 0], [11, 0, 0], [10, 0.01, 0]])  # two faces, but a sixteenth of the size long
    v = np.concatenate([m.vertices, long])
    assert topology(drop_strays(v, np.concatenate([f, sliver + len(m.vertices)]), keep=1))["pieces"] == 3
    tri = np.array([[10.0, 0, 0], [10.05, 0, 0], [10, 0.05, 0]])
    v = np.concatenate([m.vertices, tri])
    both = np.concatenate([f, sliver + len(m.vertices)])
    assert len(drop_strays(v, both, keep=1)) == len(f) - 24  # the sliver and the two small boxes


def _inside_triangle(rng: np.random.Generator) -> tuple[trimesh.Trimesh, np.ndarray]:
    """A box of random proportions, turned, and a triangle across its inside with its corners on three walls."""
    box = trimesh.creation.box(extents=rng.uniform(0.3, 2.0, 3))
    turn = trimesh.transformations.random_rotation_matrix(rng.random(3))
    half = box.extents / 2
    corners = []
    for axis in rng.permutation(3):  # one corner on a wall across each axis, the others inside the box
        c = rng.uniform(-0.5, 0.5, 3) * half
        c[axis] = half[axis] * rng.choice([-1.0, 1.0])
        corners.append(c)
    box.apply_transform(turn)
    return box, trimesh.transform_points(np.array(corners), turn)


def test_a_wide_stray_the_rest_covers_goes_given_the_input_surface():
    """A triangle across a solid's inside (wider than STRAY_SPAN, so its span alone keeps it) goes when the input's
    samples show the box's walls cover every sample near it; a part the rest does not cover stays."""
    from fastmesh.faces.pieces import STRAY_SPAN

    rng = np.random.default_rng(3)
    for _ in range(6):
        box, tri = _inside_triangle(rng)
        v = np.concatenate([box.vertices, tri])
        f = np.concatenate([box.faces, [[8, 9, 10]]])
        span = np.linalg.norm(np.ptp(tri, axis=0)) / np.linalg.norm(np.ptp(box.vertices, axis=0))
        assert span > STRAY_SPAN
        surface = trimesh.sample.sample_surface(box, 8192, seed=0)[0]
        assert len(drop_strays(v, f, keep=1)) == 13  # by its span alone, a part
        assert np.array_equal(drop_strays(v, f, keep=1, surface=surface), box.faces)
        # The same triangle as a fin the input has: its own samples are far from the box, so it stays.
        fin = tri + 3.0 * box.extents.max() * rng.normal(size=3)
        fin_samples = trimesh.sample.sample_surface(trimesh.Trimesh(fin, [[0, 1, 2]]), 200, seed=0)[0]
        v = np.concatenate([box.vertices, fin])
        assert len(drop_strays(v, f, keep=1, surface=np.concatenate([surface, fin_samples]))) == 13
        # The fin twice, as two pieces: each covers the other's samples, but once one goes the other is needed.
        v = np.concatenate([box.vertices, fin, fin])
        twice = np.concatenate([f, [[11, 12, 13]]])
        kept = drop_strays(v, twice, keep=1, surface=np.concatenate([surface, fin_samples]))
        assert len(kept) == 13 and np.array_equal(kept[:12], box.faces)


def test_vertices_far_from_the_input_are_pulled_onto_it_and_only_those():
    """A vertex beyond the limit moves onto its nearest surface sample; the others and the faces stay."""
    from fastmesh.faces.pieces import FAR_CELLS, far_limit, pull_in
    from fastmesh.tokenizer.grid import CELL

    rng = np.random.default_rng(0)
    surface = np.c_[rng.uniform(0, 10, (4000, 2)), np.zeros(4000)]  # a 10 x 10 square: 1 cell is 10/128
    limit = far_limit(surface)
    assert np.isclose(limit, FAR_CELLS * CELL * np.ptp(surface, axis=0).max())
    vertices = np.array([[5.0, 5.0, 0.5 * limit], [2.0, 3.0, 1.5 * limit], [8.0, 8.0, -3 * limit]])
    moved, which = pull_in(vertices, surface, limit)
    assert which.tolist() == [False, True, True] and np.array_equal(moved[0], vertices[0])
    assert (moved[1:, 2] == 0).all() and np.linalg.norm(moved[1:, :2] - vertices[1:, :2], axis=1).max() < 0.5


@pytest.mark.parametrize("scale", [1e-6, 1.0, 1e155])
def test_pulling_in_works_at_any_scale(scale):
    """Distances are measured in the surface's unit cube: coordinates near 1e155 (squared: inf) still move."""
    from fastmesh.faces.pieces import far_limit, pull_in

    rng = np.random.default_rng(1)
    surface = np.c_[rng.uniform(0, 10, (200, 2)), np.zeros(200)] * scale
    limit = far_limit(surface)
    vertices = np.array([[5.0, 5.0, 0.0], [2.0, 3.0, 20.0]]) * scale
    moved, which = pull_in(vertices, surface, limit)
    assert which.tolist() == [False, True] and np.array_equal(moved[0], vertices[0])
    assert moved[1, 2] == 0 and any((moved[1] == s).all() for s in surface)



def test_an_edge_crowded_with_faces_keeps_its_two_largest():
    """Four faces on the edge 0-1 (vertices made one can do that): the two largest stay, the others' edges too."""
    from fastmesh.faces.pieces import thin_crowded_edges

    v = np.array([[0, 0, 0], [1, 0, 0], [0.5, 3, 0], [0.5, -2, 0], [0.5, 0, 1], [0.5, 0, -0.5]], dtype=float)
    f = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4], [1, 0, 5], [1, 2, 4]])
    kept = thin_crowded_edges(v, f)
    assert kept.tolist() == [[0, 1, 2], [1, 0, 3], [1, 2, 4]]
    assert topology(kept)["non_manifold_edges"] == 0
    rng = np.random.default_rng(0)  # every triple of 6 points, twice: every edge crowded, every face a duplicate
    points, every = rng.normal(size=(6, 3)), np.array(list(itertools.combinations(range(6), 3)))
    kept = thin_crowded_edges(points, np.r_[every, every[:, ::-1]])
    assert 4 <= len(kept) and topology(kept)["non_manifold_edges"] == 0
    assert len({tuple(sorted(t)) for t in kept.tolist()}) == len(kept)


def test_making_whole_keeps_a_split_pinch_apart_when_it_welds_pulled_vertices():
    """A bowtie (two fans at one vertex) and a vertex far above the input's square: the pinch is split, the far
    vertex pulled onto the square, and the welding of pulled vertices leaves the pinch's two copies apart."""
    from types import SimpleNamespace

    from fastmesh.evaluation.metrics import mesh_topology
    from fastmesh.pipeline.result import whole
    from fastmesh.shapes.shape import Normalization, Shape

    rng = np.random.default_rng(0)
    square = np.c_[rng.uniform(-2, 2, (4000, 2)), np.zeros(4000)]
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [-1, 0, 0], [-1, -1, 0], [2, 0.5, 5.0]], dtype=float)
    f = np.array([[0, 1, 2], [0, 3, 4], [1, 5, 2]])
    req = SimpleNamespace(shape=Shape(vertices=square), surface_points=square, pieces_in=2,
                          frame=SimpleNamespace(norm=Normalization.fit(square)),
                          count=SimpleNamespace(low_poly_input=False))
    vertices, faces, source, pulled = whole(req, v, f)
    assert pulled == 1 and source == "model" and len(faces) == 3
    t = topology(faces)
    assert t["non_manifold_vertices"] == 0 and t["non_manifold_edges"] == 0 and t["pieces"] == 2
    assert mesh_topology(vertices, faces)["edge_manifold"]  # also with coincident vertices taken as one
