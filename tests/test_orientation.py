"""A point cloud's normals of any sign turned outward (``fastmesh.shapes.orientation``), on families drawn at
random: closed shapes of random proportions, poses and units, open ones, and the pipeline's decisions that read
the sign (closed or open, the plane rebuild)."""

from __future__ import annotations

import numpy as np
import pytest

from fastmesh.evaluation.primitives import OPEN_KINDS, RANDOM_KINDS, ROUND_KINDS, point_cloud, posed, random_shape
from fastmesh.faces.closure import decide_closed
from fastmesh.params import GenerateParams
from fastmesh.shapes import orientation
from fastmesh.shapes.io import estimate_normals, with_normals
from fastmesh.shapes.orientation import oriented, outward_signs
from fastmesh.shapes.shape import Shape

CLOSED_KINDS = RANDOM_KINDS + ROUND_KINDS
THICK_KINDS = tuple(k for k in CLOSED_KINDS if k != "tube")  # the tube's wall is thinner than a voxel


def _cloud(kind: str, rng: np.random.Generator, n: int | None = None) -> tuple[Shape, np.ndarray]:
    """Samples of a shape of ``kind`` posed at random (turned, in metres or millimetres far from the origin), their
    normals given random signs; and the outward normals (the faces' own)."""
    mesh = posed(random_shape(kind, rng), rng, turn=True, millimetres=bool(rng.random() < 0.5))
    cloud = point_cloud(mesh, n or int(rng.integers(2000, 20000)), seed=int(rng.integers(1 << 16)))
    signs = rng.choice([-1.0, 1.0], (len(cloud.vertices), 1))
    return Shape(vertices=cloud.vertices, normals=cloud.normals * signs), cloud.normals


@pytest.mark.parametrize("kind", THICK_KINDS)
def test_random_signs_on_closed_shapes_are_turned_outward(kind):
    rng = np.random.default_rng([11, len(kind), ord(kind[0])])
    for _ in range(3):
        shape, outward = _cloud(kind, rng)
        assert decide_closed(shape) == (False, "open_points")  # the signs as given enclose nothing
        turned = oriented(shape)
        agree = np.einsum("ni,ni->n", turned.normals, outward) > 0
        assert agree.mean() >= 0.95, (kind, agree.mean())
        assert np.array_equal(turned.vertices, shape.vertices)
        assert np.allclose(np.abs(np.einsum("ni,ni->n", turned.normals, shape.normals)), 1.0)  # signs only
        assert decide_closed(turned) == (True, "closed_points")


def test_a_thin_walled_tube_is_never_turned_inward():
    """Where the wall is thinner than a voxel nothing tells; what does tell is right."""
    rng = np.random.default_rng(17)
    told_any = 0
    for _ in range(4):
        shape, outward = _cloud("tube", rng)
        sign = outward_signs(shape.vertices, shape.normals)
        told = sign != 0
        assert np.array_equal(sign[told], np.sign(np.einsum("ni,ni->n", shape.normals, outward))[told])
        told_any += int(told.any())
    assert told_any >= 1  # some tubes are thick enough to tell


@pytest.mark.parametrize("kind", CLOSED_KINDS[:3])
def test_normals_that_agree_are_left_as_they_are(kind):
    """Outward normals, or all inward (Quake's models wind the other way), are the same object back."""
    shape, outward = _cloud(kind, np.random.default_rng([12, len(kind)]))
    for normals in (outward, -outward):
        given = Shape(vertices=shape.vertices, normals=normals)
        assert oriented(given) is given
        assert (outward_signs(given.vertices, normals) != 0).mean() > 0.5  # they could tell, and agreed


@pytest.mark.parametrize("kind", OPEN_KINDS)
def test_an_open_shape_has_no_inside_and_stays_open(kind):
    rng = np.random.default_rng([13, len(kind)])
    for _ in range(3):
        shape, _ = _cloud(kind, rng)
        assert not outward_signs(shape.vertices, shape.normals).any()
        assert oriented(shape) is shape and not decide_closed(shape)[0]


@pytest.mark.parametrize("kind", ["l_block", "torus", "tube"])
def test_normals_estimated_for_a_bare_cloud_point_outward(kind):
    """Without normals they are estimated from neighbours and pointed away from the centroid, which a concave part
    defeats (an L block's inner corner, a torus's hole); then turned outward where the points tell."""
    rng = np.random.default_rng([18, len(kind)])
    for _ in range(3):
        shape, outward = _cloud(kind, rng)
        bare = with_normals(Shape(vertices=shape.vertices))
        guessed = estimate_normals(shape.vertices)
        right = (np.einsum("ni,ni->n", bare.normals, outward) > 0).mean()
        assert right >= max(0.95, (np.einsum("ni,ni->n", guessed, outward) > 0).mean()) or kind == "tube"
        assert right >= (np.einsum("ni,ni->n", guessed, outward) > 0).mean()  # never fewer outward


def test_a_mesh_or_a_cloud_without_normals_is_not_touched():
    rng = np.random.default_rng(14)
    mesh = random_shape("box", rng)
    assert oriented(mesh) is mesh
    bare = Shape(vertices=point_cloud(mesh, 3000).vertices)
    assert oriented(bare) is bare


def test_the_grid_is_bounded_however_dense_the_cloud(monkeypatch):
    """A dense cloud's spacing would make a grid of billions of voxels: it stays at most MAX_SIDE across."""
    seen = []
    grid = orientation._grid
    monkeypatch.setattr(orientation, "_grid", lambda p, factor: seen.append(grid(p, factor)) or seen[-1])
    shape, outward = _cloud("box", np.random.default_rng(15), n=200_000)
    turned = oriented(shape)
    assert max(seen[0][0].shape) <= orientation.MAX_SIDE + 10
    assert (np.einsum("ni,ni->n", turned.normals, outward) > 0).mean() >= 0.95


def test_the_pipeline_reads_turned_normals_a_box_of_random_signs_comes_back_as_its_planes():
    from fastmesh.pipeline import Pipeline

    rng = np.random.default_rng(16)
    pipe = Pipeline.random("tiny", seed=0)
    for _ in range(3):
        shape, _ = _cloud("box", rng, n=8000)
        res = pipe.generate(shape, GenerateParams(seed=0, max_vertices=24))
        assert res.info["closed_decision"] == {"close": True, "reason": "closed_points"}
        assert res.info["result_from"] == "planes" and len(res.vertices) == 8 and res.quality["watertight"]
