"""Sheets that stand for thin solid parts come back as thin closed parts united with the solid
(``fastmesh.faces.slabs``)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from fastmesh.faces.defects import self_intersections
from fastmesh.faces.meshops import edge_face_counts, piece_labels, wound_alike
from fastmesh.faces.slabs import thickened


def _bent_plate(seed: int, sided: str = "both"):
    """A plate bent along x (z = bend x^2), ``thick`` thick, ``size`` across (1 mm to 1 km), turned at random and
    moved far from the origin: its mid-sheet as a 7 x 7 grid of vertices in two triangles a cell, and the input's
    samples on both faces (``sided`` "both") or on the top one only ("top"), normals outward."""
    rng = np.random.default_rng(seed)
    size = 10.0 ** rng.uniform(-3, 3)
    thick, bend = rng.uniform(0.004, 0.012), rng.uniform(-0.4, 0.4)
    g = np.linspace(-0.5, 0.5, 7)
    x, y = np.meshgrid(g, g, indexing="ij")
    mid = np.stack([x.ravel(), y.ravel(), bend * x.ravel() ** 2], 1)
    i = np.arange(36).reshape(6, 6)
    a = (i // 6) * 7 + i % 6
    sheet = np.concatenate([np.stack([a, a + 7, a + 8], -1), np.stack([a, a + 8, a + 1], -1)]).reshape(-1, 3)
    u = rng.uniform(-0.5, 0.5, (6000, 2))
    up = np.stack([-2 * bend * u[:, 0], np.zeros(len(u)), np.ones(len(u))], 1)
    up /= np.linalg.norm(up, axis=1, keepdims=True)
    on = np.stack([u[:, 0], u[:, 1], bend * u[:, 0] ** 2], 1)
    side = np.where(np.arange(len(u)) % 2 == 0, 1.0, -1.0) if sided == "both" else np.ones(len(u))
    pts, nrm = on + side[:, None] * up * thick / 2, side[:, None] * up
    turn, far = Rotation.random(random_state=seed).as_matrix(), rng.uniform(-5, 5, 3)
    place = lambda p: (p @ turn.T + far) * size  # noqa: E731
    return place(mid), sheet, place(pts), nrm @ turn.T, thick * size, size


@pytest.mark.parametrize("seed", range(6))
def test_a_sheet_with_the_input_on_both_sides_becomes_a_thin_closed_part(seed):
    """Random bent plates (any pose, mm to km): the mid-sheet comes back a slab, closed, wound alike and
    outward, crossing nothing, as thick as the plate (its volume the plate's within 15 %), every vertex on the
    input's faces (within a fifth of the thickness of a sample)."""
    v, sheet, pts, nrm, thick, size = _bent_plate(seed)
    out_v, out_f, rest, made = thickened(v, np.zeros((0, 3), dtype=np.int64), sheet, pts, nrm, 0.05 * size)
    assert made == 1 and len(rest) == 0
    assert (edge_face_counts(out_f) == 2).all() and wound_alike(out_f)
    mesh = trimesh.Trimesh(out_v, out_f, process=False)
    area = trimesh.Trimesh(v, sheet, process=False).area
    assert mesh.volume == pytest.approx(area * thick, rel=0.15)
    assert self_intersections(out_v, out_f) == 0
    from scipy.spatial import cKDTree

    assert cKDTree(pts).query(out_v[np.unique(out_f)])[0].max() < 0.2 * thick + 0.03 * size


@pytest.mark.parametrize("seed", range(3))
def test_a_sheet_with_the_input_on_one_side_stays_a_sheet(seed):
    """The same plates sampled on one face only (a true sheet): nothing is made; the sheet comes back as it
    was."""
    v, sheet, pts, nrm, _, size = _bent_plate(seed, sided="top")
    out_v, out_f, rest, made = thickened(v, np.zeros((0, 3), dtype=np.int64), sheet, pts, nrm, 0.05 * size)
    assert made == 0 and len(out_f) == 0 and np.array_equal(rest, sheet) and len(out_v) == len(v)


@pytest.mark.parametrize("seed", range(4))
def test_a_thin_part_passing_into_the_solid_is_united_with_it(seed):
    """A box (the solid) around one end of the plate, as a wing's root passes into a fuselage: one closed piece
    wound outward, crossing nothing, its volume the box's and the plate's outside it (within 15 % of the plate's);
    before, a slab that would cross the solid was not made and the sheet showed its back from one side."""
    v, sheet, pts, nrm, thick, size = _bent_plate(seed)
    # The plate's frame: its mid-sheet's first row of vertices (x = -0.5) runs along e2; the box holds x < -0.3.
    rows = v.reshape(7, 7, 3)
    e1 = rows[1, 3] - rows[0, 3]
    e1 /= np.linalg.norm(e1)
    e2 = rows[0, 6] - rows[0, 0]
    e2 /= np.linalg.norm(e2)
    e3 = np.cross(e1, e2)
    half = np.array([0.15, 0.6, 0.15]) * size
    centre = rows[0, 3] - 0.05 * size * e1
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * half
    box = trimesh.convex.convex_hull(centre + corners @ np.stack([e1, e2, e3]))
    bv, bf = np.asarray(box.vertices), np.asarray(box.faces)
    vertices = np.concatenate([bv, v])
    out_v, out_f, rest, made = thickened(vertices, bf, sheet + len(bv), pts, nrm, 0.05 * size)
    assert made == 1 and len(rest) == 0
    assert (edge_face_counts(out_f) == 2).all() and wound_alike(out_f) and piece_labels(out_f).max() == 0
    assert self_intersections(out_v, out_f) == 0
    mesh = trimesh.Trimesh(out_v, out_f, process=False)
    plate = trimesh.Trimesh(v, sheet, process=False).area * thick
    local = (v[sheet].mean(1) - centre) @ np.stack([e1, e2, e3]).T
    inside = (np.abs(local) < half).all(1).mean() * plate  # the plate's share inside the box, by its faces
    assert mesh.volume == pytest.approx(box.volume + plate - inside, abs=0.15 * plate)


def test_pieces_touching_along_a_side_are_fins_once_welded():
    """A box and a triangle whose side runs along one of the box's edges through vertices of its own at the
    same places: once welded that edge has three faces, and the triangle and the box's two faces there are fins;
    the box alone, or the triangle moved off the edge, has none."""
    from fastmesh.faces.meshops import welded_fins

    box = trimesh.creation.box((1.0, 1.0, 1.0))
    v, f = np.asarray(box.vertices), np.asarray(box.faces)
    edge = next((a, b) for a, b in box.edges_unique if np.isclose(np.abs(v[a] - v[b]).sum(), 1.0))
    tip = (v[edge[0]] + v[edge[1]]) / 2 + 2.0 * (v[edge[0]] + v[edge[1]]) / 2  # outward from the edge
    fin_v = np.concatenate([v, v[list(edge)], [tip]])
    fin_f = np.concatenate([f, [[8, 9, 10]]])
    fins = welded_fins(fin_v, fin_f)
    assert fins[-1] and fins.sum() == 3
    assert not welded_fins(v, f).any()
    moved = fin_v.copy()
    moved[8:] += 0.01 * (moved[10] - (moved[8] + moved[9]) / 2)
    assert not welded_fins(moved, fin_f).any()


def test_thin_parts_touching_along_an_edge_only_stay_edge_manifold():
    """Two triangles of a thin plate meeting at one corner (a bow tie), sampled on both faces: their prisms share
    the edge through that corner and nothing else, where a union keeps four faces on one edge once welded; those
    prisms go, and what comes back is edge-manifold once welded."""
    from fastmesh.faces.meshops import welded_in_place

    v = np.array([[0, 0, 0], [1, 0.3, 0], [1, -0.3, 0], [-1, 0.3, 0], [-1, -0.3, 0.0]])
    sheet = np.array([[0, 1, 2], [0, 4, 3]])
    rng = np.random.default_rng(0)
    u = rng.uniform(-1, 1, (8000, 2))
    inside = np.abs(u[:, 1]) < 0.3 * np.abs(u[:, 0])
    side = np.where(np.arange(len(u)) % 2 == 0, 1.0, -1.0)[inside]
    pts = np.stack([u[inside, 0], u[inside, 1], 0.005 * side], 1)
    nrm = np.stack([np.zeros(len(side)), np.zeros(len(side)), side], 1)
    out_v, out_f, rest, made = thickened(v, np.zeros((0, 3), dtype=np.int64), sheet, pts, nrm, 0.2)
    assert edge_face_counts(welded_in_place(out_v, out_f)[1]).max(initial=0) <= 2
    assert made + len(rest) > 0
