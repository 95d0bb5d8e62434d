"""Faces wound alike across their shared edges (``fastmesh.shapes.windings``): each piece the way most of its area
was wound, pieces apart from each other."""

from __future__ import annotations

import numpy as np
import trimesh

from fastmesh.shapes.windings import agreeing


def _boxes(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Two boxes of random sides apart from each other, wound outward: (V, 3) vertices, (F, 3) faces."""
    meshes = [trimesh.creation.box(rng.uniform(0.2, 2.0, 3)) for _ in range(2)]
    meshes[1].apply_translation([5.0, 0, 0])
    both = trimesh.util.concatenate(meshes)
    return np.asarray(both.vertices), np.asarray(both.faces)


def test_a_few_faces_wound_against_the_rest_turn_back():
    """Random faces of two boxes reversed (under half of each box's area): every face comes back as it was."""
    rng = np.random.default_rng(5)
    for _ in range(10):
        v, f = _boxes(rng)
        area = trimesh.Trimesh(v, f, process=False).area_faces
        turn = rng.random(len(f)) < 0.4
        for box in (slice(0, 12), slice(12, 24)):  # under half of each box's area
            while area[box][turn[box]].sum() >= 0.5 * area[box].sum():
                turn[box] &= rng.random(12) < 0.5
        flipped = f.copy()
        flipped[turn] = flipped[turn][:, ::-1]
        assert turn.any()
        assert np.array_equal(agreeing(v, flipped), f)


def test_each_piece_keeps_the_side_most_of_its_area_faces():
    """A box wound inward but for one face comes back wound inward; the other box, outward, stays so."""
    rng = np.random.default_rng(6)
    v, f = _boxes(rng)
    inward = f.copy()
    inward[:12] = inward[:12, ::-1]
    odd = inward.copy()
    odd[0] = odd[0, ::-1]
    out = agreeing(v, odd)
    assert np.array_equal(out, inward)
    assert trimesh.Trimesh(v, out, process=False).is_winding_consistent
    assert trimesh.Trimesh(v[:8], out[:12], process=False).volume < 0 < trimesh.Trimesh(v, f[12:], process=False).volume


def test_faces_wound_alike_are_left_as_they_are():
    rng = np.random.default_rng(7)
    v, f = _boxes(rng)
    assert np.array_equal(agreeing(v, f), f) and len(agreeing(v, f[:0])) == 0
