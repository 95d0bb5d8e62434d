"""The surface selection keeps every piece orientable: a face that would close a strip twisted like a Moebius band is
refused (``selection.Windings``), so the face stage's surface is wound one way wherever it is connected."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fastmesh.faces import surface_triangles as sf
from fastmesh.faces.defects import _classes, winding
from fastmesh.faces.orient import orient_faces
from fastmesh.faces.selection import Selection
from fastmesh.faces.triangles import TriangleConfig


def _band(rng: np.random.Generator, twists: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A band of ``n`` quads around a ring, turned ``twists`` half turns, at a random size, pose and unit:
    vertices (2n, 3), faces (2n, 3) with each quad's diagonal at random, and samples of it (P, 3)."""
    n = int(rng.integers(8, 21))
    radius, width = 1.0, rng.uniform(0.2, 0.5)

    def at(t, s):  # s in -1..1 across the band
        turn = twists * t / 2
        centre = np.stack([np.cos(t), np.sin(t), 0 * t], -1)
        across = np.stack([np.cos(t) * np.cos(turn), np.sin(t) * np.cos(turn), np.sin(turn)], -1)
        return radius * centre + width * s[..., None] * across

    t = 2 * np.pi * np.arange(n) / n
    v = np.stack([at(t, -np.ones(n)), at(t, np.ones(n))], 1).reshape(-1, 3)
    faces = []
    for i in range(n):
        a, b = 2 * i, 2 * i + 1
        j = (i + 1) % n
        c, d = (2 * j, 2 * j + 1) if j or twists % 2 == 0 else (1, 0)  # an odd twist joins the band's sides crossed
        faces += [(a, b, d), (a, d, c)] if rng.random() < 0.5 else [(a, b, c), (b, d, c)]
    ts, ss = rng.uniform(0, 2 * np.pi, 4000), rng.uniform(-1, 1, 4000)
    pose = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix() * 10.0 ** rng.uniform(-3, 3)
    return v @ pose.T, np.array(faces), at(ts, ss) @ pose.T


@pytest.mark.parametrize("seed", range(6))
def test_a_twisted_band_is_never_selected_whole(seed):
    """Every face of a Moebius band scores well: the selection leaves out what closes the twist, and what it takes
    is wound one way once oriented (the old selection took all of it: one edge no turning mends)."""
    rng = np.random.default_rng(seed)
    v, faces, _ = _band(rng, twists=1)
    f, _ = sf.select_faces(v, faces, rng.random(len(faces)), np.full((len(v), 2, 3), np.nan), fold_angle=1.0)
    assert len(faces) - 2 <= len(f) < len(faces)
    assert winding(v, orient_faces(v, f))["misoriented_edges"] == 0


@pytest.mark.parametrize("seed", range(3))
def test_an_untwisted_band_is_selected_whole(seed):
    """A band turned a whole turn (or not at all) is orientable: nothing is refused for its windings."""
    rng = np.random.default_rng(100 + seed)
    v, faces, _ = _band(rng, twists=2 * (seed % 2))
    f, _ = sf.select_faces(v, faces, rng.random(len(faces)), np.full((len(v), 2, 3), np.nan), fold_angle=1.0)
    assert len(f) == len(faces)
    assert winding(v, orient_faces(v, f))["misoriented_edges"] == 0


@pytest.mark.parametrize("seed", range(4))
def test_the_face_stage_surface_of_a_twisted_band_is_wound_one_way(seed):
    """The face stage's surface (selection, holes filled and closed) on a Moebius band's vertices and samples, every
    pair of near vertices an edge: wound one way where it is connected."""
    rng = np.random.default_rng(200 + seed)
    v, faces, pts = _band(rng, twists=1)
    edges = np.unique(np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [0, 2]]]), 1), axis=0)
    out_v, out_f = sf.surface_mesh(v, edges, pts, TriangleConfig(close=False))
    assert len(out_f) >= len(faces) // 2
    assert winding(out_v, out_f)["misoriented_edges"] == 0


# The six-vertex real projective plane: every edge of K6 in two faces, and no winding agrees across all of them.
PROJECTIVE_PLANE = [(0, 1, 2), (0, 2, 3), (0, 3, 4), (0, 4, 5), (0, 5, 1), (1, 2, 4), (2, 3, 5), (3, 4, 1), (4, 5, 2),
                    (5, 1, 3)]


def _facing_slow(faces: list, prefer: list) -> bool:
    """Whether ``faces`` can be wound one way across every edge of two faces with every face of a ``prefer`` 0 or
    1 turned by it (1: turned from its winding as listed), from ``defects``' classes on the double cover computed
    from scratch: the slow twin of ``Windings.asked``."""
    f = np.array(faces, dtype=np.int64).reshape(-1, 3)
    _, _, _, piece, turned, knotted = _classes(f)
    if len(knotted):
        return False
    asked = {}
    for k, p in enumerate(prefer):
        if p is not None and asked.setdefault(piece[k], p ^ int(turned[k])) != p ^ int(turned[k]):
            return False
    return True


@pytest.mark.parametrize(("twists", "told"), [(1, 0.0), (0, 0.4), (1, 0.4)])
def test_windings_equal_their_slow_twin_while_faces_come_and_go(twists, told):
    """Along a shuffled run of additions (each face wound at random, a share ``told`` of them told which way the
    input asks it to face) and removals on two projective planes and a band of ``twists`` half turns, the
    selection's verdict on a face equals the classes computed from scratch: it refuses a face exactly where no
    turning would wind the pieces it joins one way with every told face as told."""
    rng = np.random.default_rng(7 + twists)
    v, band, _ = _band(rng, twists=twists)
    faces = [tuple(t) for t in band.tolist()]
    for k in range(2):
        faces += [tuple(len(v) + 6 * k + x for x in t) for t in PROJECTIVE_PLANE]
    v = np.concatenate([v, rng.normal(size=(12, 3))])
    book = Selection(v, np.full((len(v), 2, 3), np.nan), 30.0)
    present: list[tuple] = []
    prefer: list = []
    checked = refused = 0
    for _ in range(800):
        if present and rng.random() < 0.3:
            k = int(rng.integers(len(present)))
            book.remove(*present.pop(k))
            prefer.pop(k)
            continue
        t = faces[int(rng.integers(len(faces)))]
        if any(sorted(t) == sorted(p) for p in present):
            continue
        t = t[::-1] if rng.random() < 0.5 else t
        p = int(rng.integers(2)) if rng.random() < told else None
        fast = book.windings().asked(t, book._neighbours(*t), p)[2]
        assert fast == _facing_slow(present + [t], prefer + [p])
        checked += 1
        refused += not fast
        if fast:
            book.add(*t, p)
            present.append(t)
            prefer.append(p)
    assert checked > 250 and refused > 10


@pytest.mark.parametrize("seed", range(3))
def test_a_sheet_whose_input_faces_both_ways_is_not_joined_across_the_turn(seed):
    """A flat grid of vertices on a random plane (any pose, mm to km) whose samples face one way over half of it
    and the other way over the rest: the face stage's surface joins no face of one half to one of the other
    (where the input faces one way throughout, it is one piece)."""
    from fastmesh.faces.meshops import piece_labels

    rng = np.random.default_rng(300 + seed)
    g = np.linspace(-1, 1, 9)
    x, y = np.meshgrid(g, g, indexing="ij")
    flat = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1)
    u = rng.uniform(-1, 1, (6000, 2))
    pts = np.stack([u[:, 0], u[:, 1], np.zeros(len(u))], 1)
    up = np.tile([0.0, 0.0, 1.0], (len(u), 1))
    turn = Rotation.random(random_state=seed).as_matrix()
    pose = turn * 10.0 ** rng.uniform(-3, 3)
    edges = np.argwhere(np.triu(np.linalg.norm(flat[:, None] - flat[None], axis=2) < 0.26, 1))
    cfg = TriangleConfig(close=False)
    for turned in (False, True):
        nrm = np.where((pts[:, 0] > 0.05)[:, None] & turned, -up, up)
        v, f = sf.surface_mesh(flat @ pose.T, edges, pts @ pose.T, cfg, oriented=(pts @ pose.T, nrm @ turn.T))
        label = piece_labels(f)
        centre = (v[f].mean(1) @ pose / np.linalg.det(pose) ** (2 / 3))[:, 0]  # back in the grid's frame
        if not turned:
            assert label.max() == 0 and len(f) >= 100
        else:
            left, right = set(label[centre < -0.2]), set(label[centre > 0.3])
            assert left and right and not left & right
