"""A mesh input's corners (``shapes.corners``) and the vertex stage reading them (``models.cells.raise_cells``)."""

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import cKDTree

from fastmesh.evaluation.primitives import icosphere, posed, random_shape
from fastmesh.models.cells import raise_cells
from fastmesh.pipeline import Pipeline
from fastmesh.request import Frame
from fastmesh.shapes.corners import crease_edges, mesh_corners
from fastmesh.shapes.shape import Normalization, Shape
from fastmesh.tokenizer.grid import N_CELLS, flat_index, quantize


def dense(shape: Shape, rng: np.random.Generator, size: float = 0.04) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``shape`` turned at random into its unit cube, its faces split to edges under ``size`` and its vertices
    shuffled (a dense mesh of the same surface); returns its vertices, faces and the shape's own vertices."""
    turned = posed(shape, rng)
    unit = Normalization.fit(turned.vertices).apply(turned.vertices)
    v, f = trimesh.remesh.subdivide_to_size(unit, turned.faces, size)
    order = rng.permutation(len(v))
    return v[order], np.argsort(order)[f], unit


@pytest.mark.parametrize("kind", ["box", "l_block"])
def test_boxes_and_l_blocks_of_any_proportions_and_pose_give_exactly_their_corners(kind):
    rng = np.random.default_rng(11)
    for _ in range(8):
        v, f, own = dense(random_shape(kind, rng), rng)
        found = mesh_corners(v, f)
        assert len(found) == len(own)
        assert cKDTree(own).query(found)[0].max() < 1e-9
        assert cKDTree(found).query(own)[0].max() < 1e-9


def test_every_corner_of_a_prism_is_one_of_its_vertices():
    """Prisms of 3-8 sides at random angles: a side that turns by less than ``CREASE_DEGREES`` is no crease, so
    not every vertex is found, but whatever is found is a vertex of the prism."""
    rng = np.random.default_rng(5)
    found_any = 0
    for _ in range(10):
        v, f, own = dense(random_shape("prism", rng), rng)
        found = mesh_corners(v, f)
        found_any += len(found)
        if len(found):
            assert cKDTree(own).query(found)[0].max() < 1e-9
    assert found_any >= 50


def test_a_corner_between_vertices_is_found_where_the_planes_meet():
    """The dense mesh need not have a vertex at the corner: a cube whose corners are cut by tiny triangles
    (a remesh's corner) gives the corner itself, where its three walls meet."""
    corners = np.array(np.meshgrid([-0.5, 0.5], [-0.5, 0.5], [-0.5, 0.5])).reshape(3, -1).T
    cut = np.vstack([corners[:-1], 0.5 - 0.004 * np.eye(3)])  # corner (0.5, 0.5, 0.5) cut off
    hull = trimesh.convex.convex_hull(cut)
    v, f = trimesh.remesh.subdivide_to_size(hull.vertices, hull.faces, 0.1)
    found = mesh_corners(v, f)
    d = np.linalg.norm(found - [0.5, 0.5, 0.5], axis=1)
    assert d.min() < 1e-4  # the cut's own tiny plane pulls a little
    assert len(found) == 8


def test_smooth_surfaces_have_no_corners():
    sphere = icosphere(4)
    assert len(crease_edges(sphere.vertices, sphere.faces)) == 0
    assert len(mesh_corners(sphere.vertices, sphere.faces)) == 0
    cylinder = trimesh.creation.cylinder(radius=0.4, height=0.8, sections=64)
    assert len(mesh_corners(cylinder.vertices, cylinder.faces)) == 0  # its rims turn by 5.6 degrees a vertex


def test_raise_cells_raises_only_the_cells_of_the_points_and_never_lowers():
    grid = torch.full((1, N_CELLS), -3.0)
    grid[0, 100] = 12.0
    pts = np.array([[0.1, 0.2, 0.3], [-0.4, 0.0, 0.45]])
    cells = flat_index(quantize(pts))
    grid[0, cells[1]] = 20.0
    out = raise_cells(grid, pts, 8.0)
    assert out[0, cells[0]] == 8.0 and out[0, cells[1]] == 20.0 and out[0, 100] == 12.0
    rest = torch.ones(N_CELLS, dtype=torch.bool)
    rest[torch.as_tensor(cells)] = False
    assert torch.equal(out[0, rest], grid[0, rest])
    assert grid[0, cells[0]] == -3.0  # the input grid is left as it was
    assert raise_cells(grid, np.zeros((0, 3)), 8.0) is grid


@pytest.fixture(scope="module")
def shipped():
    return Pipeline.from_pretrained(threads=1)


def test_the_vertex_stage_reads_a_mesh_inputs_corners_and_not_a_point_clouds(shipped):
    rng = np.random.default_rng(3)
    v, f, own = dense(random_shape("l_block", rng), rng)
    # Welded by the stage: a file that splits every face's corners (an STL) has the same corners.
    split = Shape(vertices=v[f].reshape(-1, 3), faces=np.arange(3 * len(f)).reshape(-1, 3))
    frame = Frame.of(split)
    cells = torch.as_tensor(flat_index(quantize(frame.norm.apply(Normalization.fit(v).invert(own)))))
    plain = shipped._logodds(frame, _params(None))
    raised = shipped._logodds(frame, _params(8.0))
    assert (raised[0, cells] >= 8.0).all() and (plain[0, cells] < 8.0).any()
    others = torch.ones(N_CELLS, dtype=torch.bool)
    others[cells] = False
    assert torch.equal(raised[0, others], plain[0, others])
    points = Shape(vertices=frame.samples(4096, 0)[0], normals=frame.samples(4096, 0)[1])
    cloud = Frame.of(points)
    assert torch.equal(shipped._logodds(cloud, _params(8.0)), shipped._logodds(cloud, _params(None)))


def _params(corner):
    from fastmesh.params import TunedParams

    return TunedParams({"corner_logodds": corner})


def test_windings_flipped_at_random_change_no_corner():
    """Faces of one file wound either way: the same creases (the normals' signs are not read), the same
    corners."""
    rng = np.random.default_rng(8)
    v, f, own = dense(random_shape("l_block", rng), rng)
    flipped = f.copy()
    turn = rng.random(len(f)) < 0.5
    flipped[turn] = flipped[turn][:, ::-1]
    a, b = mesh_corners(v, f), mesh_corners(v, flipped)
    assert len(a) == len(b) == len(own)
    assert cKDTree(a).query(b)[0].max() < 1e-9


def test_seeds_read_in_chunks_give_the_corners_read_at_once(monkeypatch):
    import fastmesh.shapes.corners as corners

    rng = np.random.default_rng(2)
    v, f, _ = dense(random_shape("prism", rng), rng)
    whole = mesh_corners(v, f)
    monkeypatch.setattr(corners, "SEED_CHUNK", 7)
    assert np.array_equal(mesh_corners(v, f), whole)


def test_a_mesh_creased_everywhere_shows_no_corners(monkeypatch):
    """Noise makes most vertices seeds: such a mesh is not read (its corners would be noise), nor one of more
    than ``MAX_SEEDS`` seeds (its cost is bounded); a low-poly mesh, all of whose vertices are seeds, is."""
    import fastmesh.shapes.corners as corners

    rng = np.random.default_rng(1)
    box = trimesh.creation.box(extents=rng.uniform(0.3, 1.0, 3))
    v, f = trimesh.remesh.subdivide_to_size(box.vertices, box.faces, 0.02)
    clean = mesh_corners(v, f)
    assert len(clean) == 8
    noisy = v + 0.002 * rng.standard_normal(v.shape)
    seeds = len(corners.corner_seeds(noisy, crease_edges(noisy, f)))
    assert seeds > corners.MAX_SEED_SHARE * len(v) and seeds > corners.FEW_SEEDS
    monkeypatch.setattr(corners, "MAX_SEED_SHARE", 1.0)
    assert len(mesh_corners(noisy, f)) > 100  # what the noise would give
    monkeypatch.undo()
    assert len(mesh_corners(noisy, f)) == 0
    assert len(mesh_corners(box.vertices, box.faces)) == 8
    monkeypatch.setattr(corners, "MAX_SEEDS", 7)
    assert len(mesh_corners(box.vertices, box.faces)) == 0


def test_a_turned_input_finds_its_corners_once_and_every_frame_reads_the_same_points(shipped, monkeypatch):
    """The canonical frame reads the corners found in the input's own frame, turned: the points it would find
    itself (up to rounding), without a second search."""
    import fastmesh.pipeline.candidate as candidate
    from fastmesh.params import GenerateParams
    from fastmesh.request import Request
    from fastmesh.shapes.canonical import canonical_rotation, frame_normals

    rng = np.random.default_rng(5)
    v, f, own = dense(random_shape("l_block", rng), rng)
    shape = Shape(vertices=v, faces=f)
    calls = []
    monkeypatch.setattr(candidate, "mesh_corners", lambda *a: calls.append(1) or mesh_corners(*a))
    req = Request.start(shape, GenerateParams())
    rotation = canonical_rotation(shape.vertices, frame_normals(shape))
    turned = Frame.of(shape, rotation)
    assert shipped._corners_in(req, req.frame) is not None and len(calls) == 1
    read = shipped._corners_in(req, turned)
    assert len(calls) == 1  # the second frame found none itself
    found = mesh_corners(*candidate.weld(turned.unit, turned.shape.faces))
    assert len(read) == len(found) == len(own)
    assert cKDTree(found).query(read)[0].max() < 1e-9
    assert shipped._corners_in(Request.start(Shape(vertices=v), GenerateParams()), req.frame) is None
    off = Request.start(shape, _params(None))
    assert shipped._corners_in(off, req.frame) is None and len(calls) == 1
