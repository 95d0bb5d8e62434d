"""The per-result quality report (fastmesh.quality) against independent computations on known meshes."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from trimesh.grouping import group_rows

from fastmesh.io import Shape, sample_surface
from fastmesh.metrics import surface_distance
from fastmesh.quality import mesh_quality, topology

KEYS = {"cd", "hd", "boundary_edges", "non_manifold_edges", "components", "watertight"}


def _trimesh_topology(m: trimesh.Trimesh) -> dict:
    """The same four facts as trimesh computes them."""
    uses = group_rows(m.edges_sorted, require_count=None)
    counts = np.array([len(g) for g in uses])
    parts = trimesh.graph.connected_components(m.edges_unique, nodes=np.unique(m.faces), min_len=1)
    return {"boundary_edges": int((counts == 1).sum()), "non_manifold_edges": int((counts > 2).sum()),
            "components": len(parts), "watertight": bool(m.is_watertight)}


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
    assert topology(cases["closed box"].faces) == {"boundary_edges": 0, "non_manifold_edges": 0, "components": 1,
                                                   "watertight": True}
    assert topology(cases["open box"].faces)["boundary_edges"] == 3  # the removed triangle's rim
    assert topology(cases["two boxes"].faces)["components"] == 2
    assert topology(cases["boxes sharing a corner"].faces)["components"] == 1
    fin = topology(cases["fin on an edge"].faces)
    assert fin == {"boundary_edges": 2, "non_manifold_edges": 1, "components": 1, "watertight": False}
    assert topology(np.zeros((0, 3), dtype=np.int64)) == {"boundary_edges": 0, "non_manifold_edges": 0,
                                                          "components": 0, "watertight": False}


def test_distance_is_zero_for_the_input_itself_and_measured_in_the_inputs_frame():
    box = _box((10.0, -4.0, 2.0), 3.0)
    shape = Shape(vertices=np.asarray(box.vertices), faces=np.asarray(box.faces))
    q = mesh_quality(box.vertices, box.faces, shape)
    assert set(q) == KEYS and q["cd"] == 0.0 and q["hd"] == 0.0 and q["watertight"] is True

    # 10 % larger about its centre: every point of either surface is at least 5 % of the size from the
    # other, a corner sqrt(3) * 5 % = 8.7 %.  Sampling only adds to the distance to the nearest sample.
    big = _box((10.0, -4.0, 2.0), 3.3)
    q = mesh_quality(big.vertices, big.faces, shape)
    assert 5.0 <= q["cd"] < 6.5 and 8.0 < q["hd"] < 11.0

    # Shifted by 10 % of the size: each shape in its own frame would hide it, the input's frame does not.
    moved = _box((10.3, -4.0, 2.0), 3.0)
    own = surface_distance((moved.vertices, moved.faces), (box.vertices, box.faces))
    q = mesh_quality(moved.vertices, moved.faces, shape)
    assert own.cd == 0.0 and q["cd"] > 3.0 and q["hd"] >= 10.0 - 1e-6


def test_point_cloud_input():
    box = _box()
    pts, nrm = sample_surface(Shape(vertices=box.vertices, faces=box.faces), 3000, seed=1)
    cloud = Shape(vertices=pts.astype(np.float64), normals=nrm.astype(np.float64))
    q = mesh_quality(box.vertices, box.faces, cloud)
    # Two samplings of one surface: only the gaps between samples remain (3,000 points on area 6).
    assert 0.0 < q["cd"] < 2.0 and q["hd"] < 8.0 and q["components"] == 1
