"""What a renderer shows (fastmesh.evaluation.visible) and the defects it sees (fastmesh.faces.defects),
against known meshes and independent computations, over random sizes, rotations and units."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from fastmesh.evaluation.exact import distance_to_mesh
from fastmesh.evaluation.visible import VIEWS, back_face_share, cameras, render_views, visible_report
from fastmesh.faces.defects import (
    defects,
    self_intersections,
    triangles_cross,
    unorientable_faces,
    unwelded_vertices,
    winding,
)
from fastmesh.faces.meshops import point_triangle_distance

SIDES = VIEWS[:4]  # the four horizontal views


def _cube() -> tuple[np.ndarray, np.ndarray]:
    b = trimesh.creation.box()
    return np.asarray(b.vertices, dtype=np.float64), np.asarray(b.faces, dtype=np.int64)


def _side(vertices: np.ndarray, faces: np.ndarray, axis: int, sign: float) -> np.ndarray:
    """Indices of the faces of an axis-aligned box on the side ``sign`` of ``axis``."""
    return np.flatnonzero(np.all(np.isclose(vertices[faces][:, :, axis], sign * 0.5), axis=1))


def _random_frame(rng: np.random.Generator):
    """A random rotation, a scale of any unit (1e-3 .. 1e3) and an offset of a few sizes."""
    rot, scale = Rotation.random(random_state=rng).as_matrix(), 10.0 ** rng.uniform(-3, 3)
    offset = rng.normal(size=3) * 5 * scale
    return lambda v: (v @ rot.T) * scale + offset


def _convex(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """The hull of random points on an ellipsoid: closed, convex, wound outward."""
    p = rng.normal(size=(int(rng.integers(30, 300)), 3))
    p = p / np.linalg.norm(p, axis=1, keepdims=True) * rng.uniform(0.2, 2.0, 3)
    hull = trimesh.PointCloud(p).convex_hull
    return np.asarray(hull.vertices), np.asarray(hull.faces)


def _sheet(n: int, cut: int) -> tuple[np.ndarray, np.ndarray]:
    """An n x n grid of unit squares, two triangles each; the squares of columns < cut wound the other way."""
    ij = np.stack(np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij"), -1).reshape(-1, 2)
    v = np.c_[ij, np.zeros(len(ij))].astype(np.float64)
    faces = []
    for i in range(n):
        for j in range(n):
            a, b, c, d = i * (n + 1) + j, (i + 1) * (n + 1) + j, (i + 1) * (n + 1) + j + 1, i * (n + 1) + j + 1
            tris = [(a, b, c), (a, c, d)]
            faces += [t[::-1] if i < cut else t for t in tris]
    return v, np.asarray(faces, dtype=np.int64)


def _folded_sphere() -> tuple[np.ndarray, np.ndarray]:
    """A closed sphere whose top cap is pushed down through its bottom: it folds through itself, and from below
    the cap's underside (the back of its faces) pokes out."""
    s = trimesh.creation.icosphere(3)
    v = np.asarray(s.vertices, dtype=np.float64).copy()
    cap = v[:, 1] > 0.5
    v[cap, 1] -= 1.7
    return v, np.asarray(s.faces)


def test_a_cube_with_one_side_flipped_shows_a_sixth_of_back_faces():
    """Each side of a cube is about a sixth of what the 14 views show (the top and bottom a little more: four
    views at 45 degrees look down on them, two on each vertical side), and every pixel shows one side: the six
    single-side flips add up to exactly 1.  The four side views show the four vertical sides alone."""
    v, f = _cube()
    assert visible_report(v, f) == {"back_face_share": 0.0}
    shares = []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            g = f.copy()
            side = _side(v, f, axis, sign)
            g[side] = g[side][:, ::-1]
            shares.append(visible_report(v, g)["back_face_share"])
            assert 0.14 < shares[-1] < (0.21 if axis == 1 else 0.17)
            share = back_face_share(render_views(v, g, cameras(v, directions=SIDES)))
            assert share == (0.0 if axis == 1 else pytest.approx(1 / 4, abs=0.01))
    assert sum(shares) == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("seed", range(6))
def test_back_faces_of_random_convex_shapes_in_any_frame(seed):
    """Closed and wound outward: no back face from any view (but for a pixel or so where a silhouette edge
    runs through a pixel centre: the rasteriser's edge tolerance lets the face behind it cover that pixel).
    Flipping a random set of faces shows exactly the pixels the rest does not: the two shares add up to 1,
    whatever the rotation, size or unit."""
    rng = np.random.default_rng(seed)
    v, f = _convex(rng)
    v = _random_frame(rng)(v)
    assert visible_report(v, f)["back_face_share"] < 1e-4
    assert visible_report(v, f[:, ::-1])["back_face_share"] > 1 - 1e-4
    flip = rng.random(len(f)) < 0.5
    one, other = f.copy(), f.copy()
    one[flip], other[~flip] = one[flip][:, ::-1], other[~flip][:, ::-1]
    a, b = visible_report(v, one)["back_face_share"], visible_report(v, other)["back_face_share"]
    assert 0.0 < a < 1.0 and a + b == pytest.approx(1.0, abs=2e-4)


@pytest.mark.parametrize("seed", range(4))
def test_silhouette_and_normal_angle_against_a_reference(seed):
    rng = np.random.default_rng(seed)
    v, f = _convex(rng)
    frame = _random_frame(rng)
    v = frame(v)
    ref = (v, f)
    same = visible_report(v, f, reference=ref)
    assert same["silhouette_iou"] == 1.0 and same["normal_angle"] == pytest.approx(0.0, abs=1e-4)
    # Turned inside out: the same pixels and, turned towards the camera, the same normals.
    inside_out = visible_report(v, f[:, ::-1], reference=ref)
    assert inside_out["silhouette_iou"] == 1.0 and inside_out["normal_angle"] == pytest.approx(0.0, abs=1e-4)
    # Half the size about the box's centre: about a quarter of the silhouette.
    centre = (v.min(0) + v.max(0)) / 2
    half = visible_report(centre + (v - centre) * 0.5, f, reference=ref)
    assert half["silhouette_iou"] == pytest.approx(0.25, abs=0.04)
    # A sphere in a cube: the same outline from the sides' centre, normals off by up to 45+ degrees.
    cube_v, cube_f = _cube()
    ball = trimesh.creation.icosphere(3, radius=0.5)
    ball_seen = visible_report(ball.vertices, ball.faces, reference=(cube_v, cube_f))
    assert 0.5 < ball_seen["silhouette_iou"] < 0.9 and 15.0 < ball_seen["normal_angle"] < 45.0


@pytest.mark.parametrize("seed", range(5))
def test_a_sheet_wound_half_one_way_half_the_other(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 12))
    cut = int(rng.integers(1, n))
    v, f = _sheet(n, cut)
    v = _random_frame(rng)(v)
    w = winding(v, f)
    # Each of the n squares along the cut has its edge on the cut wound the same way by both sides.
    assert w["misoriented_edges"] == n
    assert w["misoriented_area"] == pytest.approx(min(cut, n - cut) / n)
    assert winding(*_sheet(n, 0)) == {"misoriented_edges": 0, "misoriented_area": 0.0}


def test_a_closed_mesh_that_folds_through_itself():
    v, f = _folded_sphere()
    d = defects(v, f)
    assert d["self_intersections"] > 0 and d["misoriented_edges"] == 0  # still wound consistently
    assert visible_report(v, f)["back_face_share"] > 0.02
    s = trimesh.creation.icosphere(3)
    assert defects(s.vertices, s.faces) == {"misoriented_edges": 0, "misoriented_area": 0.0,
                                            "self_intersections": 0, "unwelded_vertices": 0}


def test_crossing_boxes_and_seams():
    v, f = _cube()
    moved = trimesh.util.concatenate([trimesh.Trimesh(v, f), trimesh.Trimesh(v + 0.5, f)])
    apart = trimesh.util.concatenate([trimesh.Trimesh(v, f), trimesh.Trimesh(v + 2.0, f)])
    touching = trimesh.util.concatenate([trimesh.Trimesh(v, f), trimesh.Trimesh(v + [1.0, 0, 0], f)])
    assert self_intersections(moved.vertices, moved.faces) > 0
    assert self_intersections(apart.vertices, apart.faces) == 0
    assert self_intersections(touching.vertices, touching.faces) == 0  # faces meet along a plane: no crossing
    # Every face with its own corners (as files split seams): 36 vertices, 28 of them coincide with another.
    soup_v, soup_f = v[f].reshape(-1, 3), np.arange(36).reshape(-1, 3)
    assert unwelded_vertices(soup_v, soup_f) == 28 and unwelded_vertices(v, f) == 0
    assert defects(soup_v, soup_f) == {"misoriented_edges": 0, "misoriented_area": 0.0, "self_intersections": 0,
                                       "unwelded_vertices": 28}


def _segment_hits(p: np.ndarray, q: np.ndarray, tri: np.ndarray) -> bool:
    """Whether segment pq crosses triangle ``tri`` (3, 3) (Moller-Trumbore, slow twin)."""
    d = q - p
    e1, e2 = tri[1] - tri[0], tri[2] - tri[0]
    h = np.cross(d, e2)
    a = e1 @ h
    if abs(a) < 1e-12:
        return False
    s = p - tri[0]
    u = (s @ h) / a
    qv = np.cross(s, e1)
    w = (d @ qv) / a
    t = (e2 @ qv) / a
    return bool(0 <= u <= 1 and 0 <= w and u + w <= 1 and 0 <= t <= 1)


def test_triangle_pairs_against_edge_crossings():
    """Two triangles in general position cross exactly when an edge of one passes through the other."""
    rng = np.random.default_rng(0)
    t1, t2 = rng.normal(size=(3000, 3, 3)), rng.normal(size=(3000, 3, 3)) * 0.7 + 0.3
    got = triangles_cross(t1, t2, 0.0)
    want = [any(_segment_hits(a[i], a[(i + 1) % 3], b) for a, b in ((x, y), (y, x)) for i in range(3))
            for x, y in zip(t1, t2, strict=True)]
    assert 200 < sum(want) < 2800 and list(got) == want


@pytest.mark.parametrize("seed", range(4))
def test_distance_to_mesh_is_the_nearest_triangle(seed):
    rng = np.random.default_rng(seed)
    v, f = _convex(rng)
    v = _random_frame(rng)(v)
    size = float(np.ptp(v, axis=0).max())
    p = v.mean(0) + rng.normal(size=(500, 3)) * size
    brute = np.array([point_triangle_distance(np.repeat(x[None], len(f), 0), v[f]).min() for x in p])
    assert np.allclose(distance_to_mesh(p, v, f), brute, rtol=1e-9, atol=1e-12 * size)


def _moebius(m: int, flipped: range) -> tuple[np.ndarray, np.ndarray]:
    """A band of m quads (two triangles each) turned half a turn around a ring; the quads in ``flipped``
    wound the other way."""
    t = 2 * np.pi * np.arange(m) / m
    ring = np.c_[np.cos(t), np.sin(t), np.zeros(m)]
    across = np.c_[np.cos(t / 2) * np.cos(t), np.cos(t / 2) * np.sin(t), np.sin(t / 2)] * 0.3
    v = np.concatenate([ring + across, ring - across])  # top i, bottom m + i

    def top(i):
        return i if i < m else m + (i - m)  # past the join top and bottom swap

    def bottom(i):
        return m + i if i < m else i - m

    faces = []
    for i in range(m):
        tris = [(top(i), bottom(i), bottom(i + 1)), (top(i), bottom(i + 1), top(i + 1))]
        faces += [t_[::-1] if i in flipped else t_ for t_ in tris]
    return v, np.asarray(faces, dtype=np.int64)


def test_a_band_no_turning_makes_agree_still_reads_its_flipped_part():
    """A Moebius band cannot be wound one way: one edge always disagrees, and no area need be turned.  With a
    quarter of it wound the other way on top, some area reads wound against the rest."""
    v, f = _moebius(12, range(0))
    w = winding(v, f)
    assert w["misoriented_edges"] == 1 and w["misoriented_area"] == 0.0
    v, f = _moebius(12, range(4, 7))
    w = winding(v, f)
    area = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    # Turning the quarter, or the part across the join from it, leaves one edge disagreeing either way: the
    # area reads one of the two (the tree's choice), never nothing.
    assert w["misoriented_edges"] == 3
    assert area[8:14].sum() / area.sum() - 1e-9 <= w["misoriented_area"] <= area[14:].sum() / area.sum() + 1e-9


@pytest.mark.parametrize("seed", range(4))
def test_faces_no_turning_makes_agree_are_those_of_a_twist_only(seed):
    """A Moebius band at any pose and unit has one edge no turning makes agree: its two faces, however its quads
    are wound and whether its vertices are split at every face (as a file's seams) or not.  Pieces that some
    turning makes agree (a sheet wound half one way, a convex shape with faces turned at random, a sphere folded
    through itself) have none."""
    rng = np.random.default_rng(seed)
    frame = _random_frame(rng)
    m = int(rng.integers(8, 20))
    start = int(rng.integers(0, m - 3))
    for flipped in (range(0), range(start, start + int(rng.integers(1, 3)))):
        v, f = _moebius(m, flipped)
        v = frame(v)
        assert unorientable_faces(v, f).sum() == 2
        soup = np.arange(3 * len(f)).reshape(-1, 3)
        assert unorientable_faces(v[f].reshape(-1, 3), soup).sum() == 2
    n = int(rng.integers(2, 10))
    assert not unorientable_faces(frame(_sheet(n, int(rng.integers(0, n)))[0]), _sheet(n, 0)[1]).any()
    v, f = _convex(rng)
    turned = f.copy()
    pick = rng.random(len(f)) < 0.3
    turned[pick] = turned[pick][:, ::-1]
    assert not unorientable_faces(frame(v), turned).any()
    assert not unorientable_faces(*_folded_sphere()).any()
