"""The quality report's distances to the exact surface and its orientation and crossing figures
(fastmesh.evaluation.quality), on known meshes in random frames."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from fastmesh.evaluation.quality import mesh_quality
from fastmesh.shapes.io import sample_surface
from fastmesh.shapes.shape import Shape
from service.schemas import Quality


def _frame(rng: np.random.Generator):
    """A random rotation, a size of any unit (1e-3 .. 1e3) and an offset."""
    rot, scale = Rotation.random(random_state=rng).as_matrix(), 10.0 ** rng.uniform(-3, 3)
    offset = rng.normal(size=3) * 5 * scale
    return lambda v: (np.asarray(v, dtype=np.float64) @ rot.T) * scale + offset


def _box(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    b = trimesh.creation.box(extents=rng.uniform(0.2, 3.0, 3))
    return np.asarray(b.vertices, dtype=np.float64), np.asarray(b.faces, dtype=np.int64)


def _subdivided(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The same surface with other triangles: each face split in four."""
    m = trimesh.Trimesh(v, f, process=False).subdivide()
    return np.asarray(m.vertices), np.asarray(m.faces)


@pytest.mark.parametrize("seed", range(5))
def test_an_exact_rebuild_reads_zero(seed):
    """A box rebuilt exactly, with other triangles than its input's, reads about 0, from its mesh and from
    8,192 points of it, in any frame (sample to sample it read about 0.8 / 2.8)."""
    rng = np.random.default_rng(seed)
    v, f = _box(rng)
    v = _frame(rng)(v)
    w, g = _subdivided(v, f)
    q = mesh_quality(w, g, Shape(vertices=v, faces=f))
    assert q["cd"] <= 0.001 and q["hd"] <= 0.001 and q["back_face_share"] < 0.001  # a silhouette pixel or so
    pts, nrm = sample_surface(Shape(vertices=v, faces=f), 8192, seed=seed)
    q = mesh_quality(w, g, Shape(vertices=pts.astype(np.float64), normals=nrm.astype(np.float64)))
    assert q["cd"] <= 0.01 and q["hd"] < 0.6
    # 2 % of the longest side out in a random direction: no point is farther than 2 %, and the corners that
    # lead come close to it (the samples miss the corners themselves).
    side = float(np.ptp(v, axis=0).max())
    moved = w + 0.02 * side * Rotation.random(random_state=rng).as_matrix()[0]
    q = mesh_quality(moved, g, Shape(vertices=v, faces=f))
    assert 0.1 < q["cd"] < 2.0 and 1.7 < q["hd"] <= 2.001


def test_a_flipped_side_and_a_fold_are_reported():
    b = trimesh.creation.box()
    v, f = np.asarray(b.vertices), np.asarray(b.faces)
    g = f.copy()
    side = np.flatnonzero(np.all(np.isclose(v[f][:, :, 0], 0.5), axis=1))
    g[side] = g[side][:, ::-1]
    q = mesh_quality(v, g, Shape(vertices=v, faces=f))
    assert 0.14 < q["back_face_share"] < 0.17 and q["misoriented_edges"] == 4
    assert q["misoriented_area"] == pytest.approx(1 / 6, abs=1e-4) and q["self_intersections"] == 0
    s = trimesh.creation.icosphere(3)
    folded = np.asarray(s.vertices).copy()
    folded[folded[:, 1] > 0.5, 1] -= 1.7  # the cap pushed down through the bottom
    q = mesh_quality(folded, s.faces, Shape(vertices=np.asarray(s.vertices), faces=np.asarray(s.faces)))
    assert q["self_intersections"] > 0 and q["back_face_share"] > 0.02 and q["watertight"]
    report = Quality(**q).model_dump()
    assert {k: report[k] for k in ("back_face_share", "misoriented_edges", "self_intersections")} == {
        k: q[k] for k in ("back_face_share", "misoriented_edges", "self_intersections")}
