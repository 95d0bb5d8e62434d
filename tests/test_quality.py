"""The per-result quality report (fastmesh.evaluation.quality) against independent computations on known meshes."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from trimesh.grouping import group_rows

from fastmesh.evaluation.metrics import surface_distance
from fastmesh.evaluation.primitives import point_cloud
from fastmesh.evaluation.quality import input_pieces, mesh_quality, topology
from fastmesh.shapes.io import sample_surface
from fastmesh.shapes.shape import Shape

KEYS = {"cd", "hd", "boundary_edges", "non_manifold_edges", "non_manifold_vertices", "components", "pieces",
        "watertight", "input_pieces", "box_gap", "back_face_share", "misoriented_edges", "misoriented_area",
        "self_intersections", "unwelded_vertices"}


def _fans(faces: np.ndarray, v: int) -> int:
    """The fans of faces around vertex ``v``, walked face to face across the edges at ``v`` (slow twin)."""
    around = [tuple(f) for f in faces.tolist() if v in f]
    seen, fans = set(), 0
    for start in around:
        if start in seen:
            continue
        fans += 1
        stack = [start]
        while stack:
            f = stack.pop()
            if f in seen:
                continue
            seen.add(f)
            stack += [g for g in around if g not in seen and len((set(f) & set(g)) - {v}) == 1]
    return fans


def _trimesh_topology(m: trimesh.Trimesh) -> dict:
    """The same facts as trimesh computes them (non-manifold vertices by walking each vertex's fans)."""
    uses = group_rows(m.edges_sorted, require_count=None)
    counts = np.array([len(g) for g in uses])
    parts = trimesh.graph.connected_components(m.edges_unique, nodes=np.unique(m.faces), min_len=1)
    return {"boundary_edges": int((counts == 1).sum()), "non_manifold_edges": int((counts > 2).sum()),
            "non_manifold_vertices": sum(_fans(m.faces, v) > 1 for v in np.unique(m.faces)),
            "components": len(parts), "pieces": _edge_pieces(m.faces), "watertight": bool(m.is_watertight)}


def _edge_pieces(faces: np.ndarray) -> int:
    """Groups of faces joined through shared edges, by union-find over each edge's faces (slow twin; trimesh's
    face adjacency leaves out edges of three faces)."""
    parent = list(range(len(faces)))

    def root(i):
        while parent[i] != i:
            i = parent[i]
        return i

    first = {}
    for i, (a, b, c) in enumerate(faces.tolist()):
        for e in ((a, b), (b, c), (c, a)):
            j = first.setdefault(tuple(sorted(e)), i)
            parent[root(i)] = root(j)
    return len({root(i) for i in range(len(faces))})


def _box(offset=(0.0, 0.0, 0.0), scale=1.0) -> trimesh.Trimesh:
    m = trimesh.creation.box()
    return trimesh.Trimesh(m.vertices * scale + np.asarray(offset), m.faces, process=False)


def _cases() -> dict[str, trimesh.Trimesh]:
    box = _box()
    open_box = trimesh.Trimesh(box.vertices, box.faces[1:], process=False)
    two = trimesh.util.concatenate([box, _box((3.0, 0.0, 0.0))])
    corner = trimesh.util.concatenate([box, _box((1.0, 1.0, 1.0))])  # share one corner point, not merged
    corner.merge_vertices()
    a, b = box.faces[0][:2]
    fin = trimesh.Trimesh(np.vstack([box.vertices, [[2.0, 2.0, 2.0]]]), np.vstack([box.faces, [[a, b, 8]]]),
                          process=False)
    return {"closed box": box, "open box": open_box, "two boxes": two, "boxes sharing a corner": corner,
            "fin on an edge": fin, "sphere": trimesh.creation.icosphere(2)}


@pytest.mark.parametrize("name", list(_cases()))
def test_topology_matches_trimesh(name):
    m = _cases()[name]
    assert topology(m.faces) == _trimesh_topology(m)


def test_known_values():
    cases = _cases()
    assert topology(cases["closed box"].faces) == {"boundary_edges": 0, "non_manifold_edges": 0,
                                                   "non_manifold_vertices": 0, "components": 1, "pieces": 1,
                                                   "watertight": True}
    assert topology(cases["open box"].faces)["boundary_edges"] == 3  # the removed triangle's rim
    assert topology(cases["two boxes"].faces)["components"] == 2
    corner = topology(cases["boxes sharing a corner"].faces)
    assert corner["components"] == 1 and corner["pieces"] == 2 and corner["non_manifold_vertices"] == 1
    fin = topology(cases["fin on an edge"].faces)
    assert fin == {"boundary_edges": 2, "non_manifold_edges": 1, "non_manifold_vertices": 0, "components": 1,
                   "pieces": 1, "watertight": False}
    assert topology(np.zeros((0, 3), dtype=np.int64)) == {"boundary_edges": 0, "non_manifold_edges": 0,
                                                          "non_manifold_vertices": 0, "components": 0, "pieces": 0,
                                                          "watertight": False}


def test_distance_is_zero_for_the_input_itself_and_measured_in_the_inputs_frame():
    box = _box((10.0, -4.0, 2.0), 3.0)
    shape = Shape(vertices=np.asarray(box.vertices), faces=np.asarray(box.faces))
    q = mesh_quality(box.vertices, box.faces, shape)
    assert set(q) == KEYS and q["cd"] == 0.0 and q["hd"] == 0.0 and q["watertight"] is True and q["box_gap"] == 0.0

    # 10 % larger about its centre: every point of either surface is at least 5 % of the size from the
    # other (a point of the smaller box exactly 5 %), a corner sqrt(3) * 5 % = 8.66 %.
    big = _box((10.0, -4.0, 2.0), 3.3)
    q = mesh_quality(big.vertices, big.faces, shape)
    assert 5.0 <= q["cd"] < 5.5 and 7.5 < q["hd"] <= 8.661
    assert q["box_gap"] == pytest.approx(5.0, abs=1e-3)  # each side 0.15 out of 3.0

    # Shifted by 10 % of the size: each shape in its own frame would hide it, the input's frame does not.
    moved = _box((10.3, -4.0, 2.0), 3.0)
    own = surface_distance((moved.vertices, moved.faces), (box.vertices, box.faces))
    q = mesh_quality(moved.vertices, moved.faces, shape)
    assert own.cd == 0.0 and q["cd"] > 3.0 and q["hd"] >= 10.0 - 1e-6
    assert q["box_gap"] == pytest.approx(10.0, abs=1e-3)


def test_point_cloud_input():
    box = _box()
    pts, nrm = sample_surface(Shape(vertices=box.vertices, faces=box.faces), 3000, seed=1)
    cloud = Shape(vertices=pts.astype(np.float64), normals=nrm.astype(np.float64))
    q = mesh_quality(box.vertices, box.faces, cloud)
    # The points lie on the box and the box on the discs they stand for: only where the discs leave a gap
    # does the result stand off them (sample to sample, 3,000 points on area 6 read about 1 / 4).
    assert q["cd"] < 0.05 and q["hd"] < 1.0 and q["components"] == 1 and q["input_pieces"] == 1


def test_the_same_mesh_gets_the_same_report():
    """The samples have a fixed seed: two reports of one mesh against one input are equal."""
    box, sphere = _box(), trimesh.creation.icosphere(2)
    shape = Shape(vertices=np.asarray(sphere.vertices), faces=np.asarray(sphere.faces))
    assert mesh_quality(box.vertices, box.faces, shape) == mesh_quality(box.vertices.copy(), box.faces, shape)


@pytest.mark.parametrize("kind", ["mesh", "points"])
def test_input_pieces_of_meshes_and_point_clouds(kind):
    rng = np.random.default_rng(3)
    for n in (1, 2, 3):
        # n boxes of random sizes, apart by at least half the largest; the mesh's seams split (welded back).
        boxes = []
        for i in range(n):
            b = trimesh.creation.box(extents=rng.uniform(0.5, 1.0, 3))
            b.apply_translation([2.0 * i, 0.0, 0.0])
            boxes.append(trimesh.Trimesh(b.vertices[b.faces].reshape(-1, 3), np.arange(36).reshape(-1, 3),
                                         process=False))
        m = trimesh.util.concatenate(boxes)
        shape = Shape(vertices=np.asarray(m.vertices), faces=np.asarray(m.faces))
        assert input_pieces(shape if kind == "mesh" else point_cloud(shape, 4000, seed=n)) == n
