"""Edges turned where the other diagonal of their two triangles fits the input better (``faces.swap``), and the
pipeline's use of it on a generated result (``pipeline.result.swapped``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from fastmesh.evaluation.metrics import mesh_topology
from fastmesh.evaluation.quality import topology
from fastmesh.faces.support import surface_fit
from fastmesh.faces.swap import pairs_before_after, swap_edges, turnable
from fastmesh.params import GenerateParams
from fastmesh.pipeline import result as step8
from fastmesh.request import Request
from fastmesh.shapes.shape import Shape

DATA = Path(__file__).parent / "data"


def _samples(mesh: trimesh.Trimesh, n: int = 8192) -> tuple[np.ndarray, np.ndarray]:
    points, index = trimesh.sample.sample_surface(mesh, n, seed=0)
    return np.asarray(points), np.asarray(mesh.face_normals[index])


def _triangles(faces: np.ndarray) -> set[tuple[int, ...]]:
    """Each face as its corners from the smallest on, so the winding is kept and the start forgotten."""
    out = set()
    for f in np.asarray(faces).tolist():
        k = f.index(min(f))
        out.add(tuple(f[k:] + f[:k]))
    return out


def _miscut(mesh: trimesh.Trimesh, rng: np.random.Generator, n: int) -> tuple[np.ndarray, int]:
    """``mesh``'s faces with up to ``n`` random edges turned (no two sharing a face): the same vertices with
    diagonals that cut across the surface."""
    f = np.asarray(mesh.faces, dtype=np.int64).copy()
    pairs = turnable(f)
    _, new = pairs_before_after(pairs)
    used, turned = np.zeros(len(f), dtype=bool), 0
    for e in rng.permutation(len(pairs))[: 4 * n]:
        f1, f2 = pairs[e, 4:]
        if used[f1] or used[f2] or turned == n:
            continue
        used[f1] = used[f2] = True
        f[f1], f[f2] = new[e]
        turned += 1
    return f, turned


def test_a_roof_cut_along_its_valley_turns_to_its_ridge():
    """A square whose two opposite corners are raised is a roof over the diagonal between them; cut along the
    other diagonal it is a valley.  Its edge turns, to exactly the roof's two triangles, wound as they were;
    and the roof itself, and a flat square cut either way, keep their faces."""
    v = np.array([[0, 0, 0], [1, 0, 0.5], [1, 1, 0], [0, 1, 0.5]], dtype=np.float64)
    roof = np.array([[0, 1, 3], [1, 2, 3]])
    valley = np.array([[0, 1, 2], [0, 2, 3]])
    points = _samples(trimesh.Trimesh(v, roof, process=False), 4096)
    faces, turned = swap_edges(v, valley, *points)
    assert turned == 1 and _triangles(faces) == _triangles(roof)
    assert swap_edges(v, roof, *points)[1] == 0
    flat = v * [1, 1, 0]
    points = _samples(trimesh.Trimesh(flat, roof, process=False), 4096)
    for cut in (roof, valley):
        assert swap_edges(flat, cut, *points)[1] == 0



def test_a_turn_that_would_cross_another_face_is_turned_back():
    """The valley under the roof's samples, a fin standing over its diagonal that the roof would pass through:
    turned as before, the roof's triangles cross the fin; with ``uncrossed`` the edge stays (the valley crosses
    nothing), and with the fin away it turns as before."""
    from fastmesh.faces.crossings import crossing_faces

    v = np.array([[0, 0, 0], [1, 0, 0.5], [1, 1, 0], [0, 1, 0.5]], dtype=np.float64)
    roof, valley = np.array([[0, 1, 3], [1, 2, 3]]), np.array([[0, 1, 2], [0, 2, 3]])
    points = _samples(trimesh.Trimesh(v, roof, process=False), 4096)
    fin = np.array([[0.3, 0.3, 0.1], [0.6, 0.6, 0.1], [0.45, 0.45, 0.6]])
    both, faces = np.vstack([v, fin]), np.vstack([valley, [[4, 5, 6]]])
    free, turned = swap_edges(both, faces, *points)
    assert turned == 1 and crossing_faces(both, free).any()
    kept, turned = swap_edges(both, faces, *points, uncrossed=True)
    assert turned == 0 and np.array_equal(kept, faces) and not crossing_faces(both, kept).any()
    away = np.vstack([v, fin + [5.0, 0.0, 0.0]])
    assert swap_edges(away, faces, *points, uncrossed=True)[1] == 1


def test_a_pair_whose_quad_is_not_convex_never_turns():
    """A dart: the pair's shared edge runs from its notch, so the other diagonal lies outside it and one turned
    triangle would lie folded back over the other (a sliver showing its back).  Such a pair is never turned,
    whatever the input says; the same pair with its notch pushed out (a convex quad) may turn."""
    from fastmesh.faces.swap import _unfolded

    dart = np.array([[0, 0, 0], [2, 0, 0], [-1, 1, 0.2], [-1, -1, 0.2]], dtype=np.float64)
    faces = np.array([[0, 1, 2], [1, 0, 3]])
    pairs = turnable(faces)
    old, new = pairs_before_after(pairs)
    assert len(pairs) == 1 and not _unfolded(dart, old, new).any()
    convex = dart * [1, 1, 1] + [[-2, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0]]
    assert _unfolded(convex, old, new).all()
    folded = trimesh.Trimesh(dart, new[0], process=False)  # the input lies along the turned, folded pair
    assert swap_edges(dart, faces, *_samples(folded, 2048))[1] == 0

def test_miscut_ellipsoids_of_a_random_family_are_cut_back():
    """Ellipsoids of random axes, turns, units and places, a tenth of their edges turned across the surface: the
    swap turns most of them back (at least 80 % of the faces as they were), the mesh nearer its input than the
    miscut one, closed, edge-manifold, wound alike, with every vertex where it was."""
    rng = np.random.default_rng(11)
    for _ in range(5):
        sphere = trimesh.creation.icosphere(2)
        scale = 10 ** rng.uniform(-2, 2)
        turn = trimesh.transformations.random_rotation_matrix(rng.random(3))[:3, :3]
        axes = rng.uniform(0.3, 1.0, 3)
        v = (np.asarray(sphere.vertices) * axes) @ turn.T * scale + rng.uniform(-100, 100, 3) * scale
        truth = trimesh.Trimesh(v, sphere.faces, process=False)
        points, normals = _samples(truth, 16384)
        miscut, n = _miscut(truth, rng, len(truth.edges_unique) // 10)
        assert n > 10
        faces, turned = swap_edges(v, miscut, points, normals)
        assert turned >= n // 2
        assert len(_triangles(faces) & _triangles(truth.faces)) >= 0.8 * len(faces)
        assert surface_fit(v, faces, points) < surface_fit(v, miscut, points)
        t = topology(faces)
        assert t["watertight"] and t["non_manifold_edges"] == 0 and t["pieces"] == 1
        directed = np.c_[faces[:, :2], faces[:, 1:], faces[:, [2, 0]]].reshape(-1, 2)
        assert len(np.unique(directed, axis=0)) == len(directed)  # each edge once each way: wound alike


def test_open_and_non_manifold_edges_never_turn():
    """Only an edge of two faces wound alike turns: a boundary edge, an edge of three faces and an edge between
    faces wound against each other are not offered, and a turn never makes an edge the mesh has."""
    faces = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4], [1, 2, 5], [5, 2, 6]])
    pairs = turnable(faces)
    edges = {tuple(sorted(p[:2])) for p in pairs.tolist()}
    assert (0, 1) not in edges  # three faces
    assert (1, 2) not in edges  # wound against each other: 1->2 in both
    assert edges == {(2, 5)}
    tetra = trimesh.creation.icosahedron()
    assert len(turnable(np.asarray(tetra.faces))) == len(tetra.edges_unique)
    closed_tetra = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
    assert len(turnable(closed_tetra)) == 0  # every other diagonal is an edge already


def test_a_result_with_split_pinches_stays_edge_manifold_once_welded():
    """The generated wheel with 25 pinches split into copies at one position, as the pipeline holds it: turned
    (``step8.swapped``), welded by position it has no edge of three faces and stays closed, with its face count;
    the same wheel as it comes back where nothing turns."""
    data = np.load(DATA / "pinched_wheel.npz")
    v, f = data["vertices"].astype(np.float64), data["faces"].astype(np.int64)
    shape = Shape(vertices=data["points"].astype(np.float64), normals=data["normals"].astype(np.float64))
    req = Request.start(shape, GenerateParams())
    sv, sf, turned = step8.swapped(req, v, f)
    assert turned > 0 and len(sf) == len(f)
    t = mesh_topology(sv, sf)
    assert t["edge_manifold"] and t["watertight"]
    assert surface_fit(sv, sf, shape.vertices) <= surface_fit(v, f, shape.vertices)
    box = trimesh.creation.box((1.0, 2.0, 0.5))
    points, normals = _samples(box)
    req = Request.start(Shape(vertices=points, normals=normals), GenerateParams())
    same = step8.swapped(req, np.asarray(box.vertices), np.asarray(box.faces))
    assert same[2] == 0 and same[1] is not None and np.array_equal(same[1], box.faces)
