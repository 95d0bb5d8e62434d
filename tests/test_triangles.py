"""Faces from adjacency: 3-cycle enumeration, clean-up, orientation, and corpus recovery."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import scipy.sparse as sp
import trimesh
from testdata import committed_meshes, shared_corpus_sample

from fastmesh.faces import cliques as cl
from fastmesh.faces import mesh_from_adjacency
from fastmesh.faces import triangles as fm
from fastmesh.faces.meshops import edges_from_faces, remove_unreferenced, triangle_areas
from fastmesh.faces.orient import orient_faces
from fastmesh.shapes.io import load_shape
from fastmesh.shapes.shape import Normalization
from fastmesh.tokenizer import dequantize, quantize_mesh

# The paper's rule alone: every 3-clique of the edges, none of the shipped clean-up.
RULE = {"selection": "cliques", "drop_coplanar_diagonals": False, "support_tol": None, "max_faces_per_edge": None,
        "remove_unreferenced": False}


def _brute_triangles(adj: np.ndarray) -> np.ndarray:
    n = len(adj)
    out = [t for t in itertools.combinations(range(n), 3) if adj[t[0], t[1]] and adj[t[1], t[2]] and adj[t[0], t[2]]]
    return np.array(out, dtype=np.int64).reshape(-1, 3)


def _grid(k: int):
    idx = np.arange(k * k).reshape(k, k)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    f = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    x, y = np.meshgrid(np.arange(k), np.arange(k), indexing="ij")
    v = np.stack([x, y, np.zeros_like(x)], -1).reshape(-1, 3).astype(float)
    return v, f


@pytest.mark.parametrize("seed", range(5))
def test_triangles_match_brute_force(seed):
    rng = np.random.default_rng(seed)
    n = 30
    adj = rng.random((n, n)) < 0.25
    adj = np.triu(adj, 1)
    adj = adj | adj.T
    expect = _brute_triangles(adj)
    assert np.array_equal(cl.triangles_from_adjacency(adj), expect)
    assert np.array_equal(cl.triangles_from_adjacency(adj.astype(np.float32)), expect)
    assert np.array_equal(cl.triangles_from_adjacency(sp.csr_matrix(adj)), expect)
    assert np.array_equal(cl.triangles_from_adjacency(np.argwhere(np.triu(adj)), n), expect)
    # A directed (upper-triangular) matrix is symmetrised.
    assert np.array_equal(cl.triangles_from_adjacency(np.triu(adj)), expect)


def test_chunked_enumeration(monkeypatch):
    rng = np.random.default_rng(7)
    adj = rng.random((40, 40)) < 0.4
    adj = np.triu(adj, 1) | np.triu(adj, 1).T
    monkeypatch.setattr(cl, "_CHUNK", 5)
    assert np.array_equal(cl.triangles_from_adjacency(adj), _brute_triangles(adj))
    quads = cl.cliques4(adj)
    brute = [q for q in itertools.combinations(range(40), 4) if all(adj[a, b] for a, b in itertools.combinations(q, 2))]
    assert np.array_equal(quads, np.array(brute).reshape(-1, 4))


def test_small_and_bad_inputs():
    assert cl.triangles_from_adjacency(np.zeros((0, 2), dtype=int)).shape == (0, 3)
    assert cl.triangles_from_adjacency(np.ones((2, 2), dtype=bool)).shape == (0, 3)
    k4 = np.ones((4, 4), dtype=bool)
    assert len(cl.triangles_from_adjacency(k4)) == 4  # the diagonal is ignored
    with pytest.raises(ValueError):
        cl.as_edges(np.zeros((3, 4)))
    with pytest.raises(ValueError):
        cl.as_edges(np.array([[0, 5]]), n_vertices=3)


def test_large_dense_grid_adjacency():
    v, f = _grid(63)  # 3969 vertices, dense 3969 x 3969 bool matrix
    e = edges_from_faces(f)
    adj = np.zeros((len(v), len(v)), dtype=bool)
    adj[e[:, 0], e[:, 1]] = True
    tri = cl.triangles_from_adjacency(adj)
    assert np.array_equal(tri, np.unique(np.sort(f, 1), axis=0))  # a triangulated grid has no other 3-cycles


def test_drop_degenerate():
    v = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0]], dtype=float)
    f = np.array([[0, 1, 2], [0, 1, 3], [3, 1, 0], [1, 1, 3]])  # collinear, good, duplicate, repeated index
    assert fm.drop_degenerate(v, f).tolist() == [[0, 1, 3]]


def test_coplanar_convex_quad_keeps_shorter_diagonal():
    v = np.array([[0, 0, 0], [4, 0, 0], [4, 1, 0], [0, 1, 0]], dtype=float)
    tri = cl.triangles_from_adjacency(np.ones((4, 4), dtype=bool))
    out = fm.drop_coplanar_diagonals(v, tri)
    assert len(out) == 2
    assert len(edges_from_faces(out)) == 5  # four sides and one diagonal
    tetra = v + np.array([[0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 3.0]])
    assert len(fm.drop_coplanar_diagonals(tetra, tri)) == 4  # not flat: untouched


def test_coplanar_inner_point_drops_outer_triangle():
    v = np.array([[0, 0, 0], [4, 0, 0], [0, 4, 0], [1, 1, 0]], dtype=float)
    tri = cl.triangles_from_adjacency(np.ones((4, 4), dtype=bool))
    out = fm.drop_coplanar_diagonals(v, tri)
    assert sorted(map(tuple, np.sort(out, 1))) == [(0, 1, 3), (0, 2, 3), (1, 2, 3)]
    assert len(fm.drop_coplanar_diagonals(v, tri, cases=("convex",))) == 4


def test_orientation_sphere_with_random_flips():
    s = trimesh.creation.icosphere(subdivisions=2)
    f = np.asarray(s.faces).copy()
    rng = np.random.default_rng(0)
    flip = rng.random(len(f)) < 0.5
    f[flip] = f[flip][:, ::-1]
    out = orient_faces(s.vertices, f)
    m = trimesh.Trimesh(s.vertices, out, process=False)
    assert m.is_winding_consistent and m.volume > 0
    assert np.array_equal(np.sort(out, 1), np.sort(f, 1))  # same faces, same order


def test_orientation_inverted_parts_and_open_surface():
    s = trimesh.creation.icosphere(subdivisions=1)
    v2 = np.concatenate([s.vertices, s.vertices + 5])
    f2 = np.concatenate([s.faces[:, ::-1], s.faces + len(s.vertices)])  # first sphere inside out
    out = orient_faces(v2, f2)
    m = trimesh.Trimesh(v2, out, process=False)
    assert m.is_winding_consistent
    assert all(p.volume > 0 for p in m.split(only_watertight=False))
    v, f = _grid(10)
    f = f.copy()
    f[::3] = f[::3, ::-1]
    assert trimesh.Trimesh(v, orient_faces(v, f), process=False).is_winding_consistent


def test_mesh_from_adjacency_recovers_sphere():
    s = trimesh.creation.icosphere(subdivisions=2)
    adj = edges_from_faces(s.faces)
    v, f = mesh_from_adjacency(s.vertices, adj, fm.TriangleConfig(**RULE))
    m = trimesh.Trimesh(v, f, process=False)
    assert len(f) == len(s.faces) and m.is_winding_consistent and m.volume > 0
    v3, f3 = mesh_from_adjacency(np.concatenate([s.vertices, [[9, 9, 9]]]), adj,
                                    fm.TriangleConfig(selection="cliques"))
    assert len(v3) == len(s.vertices) and len(f3) == len(s.faces)


def test_remove_unreferenced():
    v = np.arange(15, dtype=float).reshape(5, 3)
    nv, nf, kept = remove_unreferenced(v, np.array([[4, 1, 3]]))
    assert kept.tolist() == [1, 3, 4] and nf.tolist() == [[2, 0, 1]] and np.array_equal(nv, v[[1, 3, 4]])


@pytest.mark.parametrize("path", committed_meshes() + shared_corpus_sample(12), ids=lambda p: p.name[:40])
def test_corpus_ground_truth_triangles_recovered(path):
    shape = load_shape(path)
    q, f, _ = quantize_mesh(Normalization.fit(shape.vertices).apply(shape.vertices), shape.faces)
    n = len(q)
    tri = cl.triangles_from_adjacency(edges_from_faces(f), n)

    def key(a):
        s = np.sort(a, 1)
        return (s[:, 0] * n + s[:, 1]) * n + s[:, 2]

    assert np.isin(key(f), key(tri)).all()  # every ground-truth face is a 3-cycle
    assert len(tri) >= len(f)
    # Clean-up only removes triangles, and never a ground-truth face of non-zero area.  (The removal of flat
    # vertices, its last step, replaces faces by larger ones: tests/test_simplify.py.)
    x = dequantize(q)
    v, out = mesh_from_adjacency(x, edges_from_faces(f), fm.TriangleConfig(**RULE, flat_tol=None))
    nonzero = f[triangle_areas(x, f) > 1e-10]
    assert np.isin(key(nonzero), key(out)).all()
    assert len(out) <= len(tri)


def test_limit_faces_per_edge_keeps_the_best_faces_and_makes_edges_manifold():
    # Five faces around edge (0, 1): a fan of fins.  Best two (lowest score) stay.
    faces = np.array([[0, 1, 2], [0, 1, 3], [1, 0, 4], [0, 1, 5], [0, 1, 6]])
    score = np.array([0.5, 0.1, 0.3, 0.2, 0.9])
    kept = fm.limit_faces_per_edge(faces, score, max_per_edge=2)
    assert kept.tolist() == [[0, 1, 3], [0, 1, 5]]  # original order, best two by score
    # A closed mesh is already manifold: nothing goes.
    sphere = trimesh.creation.icosphere(1)
    assert len(fm.limit_faces_per_edge(sphere.faces, np.zeros(len(sphere.faces)))) == len(sphere.faces)
    # A face whose every edge is free stays even when it scores worst.
    lone = np.concatenate([faces, [[7, 8, 9]]])
    assert [7, 8, 9] in fm.limit_faces_per_edge(lone, np.append(score, 99.0)).tolist()


def test_mesh_from_adjacency_limits_faces_per_edge_when_asked():
    # K5 on a convex position: 10 triangles, every edge in 3 of them.
    rng = np.random.default_rng(0)
    v = rng.normal(size=(5, 3))
    edges = np.array([(i, j) for i in range(5) for j in range(i + 1, 5)])
    _, f_all = mesh_from_adjacency(v, edges, fm.TriangleConfig(**RULE, orient=False))
    _, f_lim = mesh_from_adjacency(v, edges, fm.TriangleConfig(**{**RULE, "max_faces_per_edge": 2}, orient=False))
    assert len(f_all) == 10 and 0 < len(f_lim) < 10
    e = np.sort(np.concatenate([f_lim[:, [0, 1]], f_lim[:, [1, 2]], f_lim[:, [2, 0]]]), axis=1)
    assert np.unique(e, axis=0, return_counts=True)[1].max() <= 2
