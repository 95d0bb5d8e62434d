"""Kitbashed mesh inputs (``fastmesh.faces.kitbash``): closed parts that touch or overlap come back as their union,
rebuilt from its planes, on random families scored against the true union (the parts' surfaces with nothing just in
front of them) with exact distances."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from fastmesh.faces.kitbash import flat_regions, kitbash_union
from fastmesh.faces.meshops import distance_to_triangles
from fastmesh.faces.plane_cells import plane_cells
from fastmesh.params import GenerateParams
from fastmesh.pipeline import Pipeline
from fastmesh.shapes.planar import PlanarConfig, polyhedron
from fastmesh.shapes.shape import Normalization, Shape


def _box(lo, hi, turn: float = 0.0) -> trimesh.Trimesh:
    """An axis-aligned box from ``lo`` to ``hi``, turned by ``turn`` radians about the vertical through its centre."""
    b = trimesh.creation.box(bounds=[lo, hi])
    if turn:
        b.apply_transform(trimesh.transformations.rotation_matrix(turn, [0, 1, 0], (np.array(lo) + hi) / 2))
    return b


def _joined(parts: list[trimesh.Trimesh]) -> tuple[np.ndarray, np.ndarray]:
    """One mesh of all the parts, each with its own vertices (as an artist's file keeps them)."""
    vertices, faces, at = [], [], 0
    for p in parts:
        vertices.append(np.asarray(p.vertices))
        faces.append(np.asarray(p.faces) + at)
        at += len(p.vertices)
    return np.vstack(vertices), np.vstack(faces)


def _chair() -> list[trimesh.Trimesh]:
    """Six boxes: four legs going 0.05 into the seat, the back standing flush on the seat's rim."""
    legs = [_box([x, 0, z], [x + 0.1, 0.55, z + 0.1]) for x in (0, 0.9) for z in (0, 0.9)]
    return legs + [_box([0, 0.5, 0], [1, 0.6, 1]), _box([0, 0.6, 0.9], [1, 1.4, 1])]


def _random_prop(rng: np.random.Generator) -> list[trimesh.Trimesh]:
    """3-7 boxes of random proportions, each touching (a face flush on a side of an earlier one) or overlapping
    (its centre inside an earlier one) another not turned; one in three of those overlapping turned about the
    vertical."""
    parts = [_box(-rng.uniform(0.2, 1, 3) / 2, rng.uniform(0.2, 1, 3) / 2)]
    hosts = [parts[0].bounds]  # the boxes not turned: their bounds are their sides
    for _ in range(int(rng.integers(2, 7))):
        host = hosts[int(rng.integers(len(hosts)))]
        size = rng.uniform(0.1, 0.8, 3)
        centre = rng.uniform(host[0], host[1])
        if rng.random() < 0.5:  # flush on one of the host's sides
            axis, side = int(rng.integers(3)), int(rng.integers(2))
            centre[axis] = host[side, axis] + (size[axis] / 2 if side else -size[axis] / 2)
            turn = 0.0
        else:
            turn = rng.uniform(0.2, 1.2) if rng.random() < 0.33 else 0.0
        parts.append(_box(centre - size / 2, centre + size / 2, turn))
        if not turn:
            hosts.append(parts[-1].bounds)
    return parts


def _posed(parts: list[trimesh.Trimesh], rng: np.random.Generator, scale: float) -> list[trimesh.Trimesh]:
    """The prop turned at random, scaled by ``scale`` and moved up to 10 of its sizes from the origin."""
    pose = trimesh.transformations.random_rotation_matrix(rng.random(3))
    pose[:3, :3] *= scale
    pose[:3, 3] = rng.uniform(-10, 10, 3) * scale
    return [p.copy().apply_transform(pose) for p in parts]


def _inside_parts(points: np.ndarray, parts: list[trimesh.Trimesh]) -> np.ndarray:
    """Whether each point lies inside one of the box parts (each a convex hull: behind all its face planes)."""
    inside = np.zeros(len(points), dtype=bool)
    for p in parts:
        off = points @ p.face_normals.T - np.einsum("ij,ij->i", p.face_normals, p.triangles[:, 0])
        inside |= (off < 0).all(1)
    return inside


def _winding(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The winding number of a closed mesh about each point (1 inside, 0 outside: Van Oosterom and Strackee)."""
    a, b, c = (vertices[faces[:, k]][None] - points[:, None] for k in range(3))
    la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
    det = np.einsum("nfi,nfi->nf", a, np.cross(b, c))
    div = (la * lb * lc + np.einsum("nfi,nfi->nf", a, b) * lc + np.einsum("nfi,nfi->nf", b, c) * la
           + np.einsum("nfi,nfi->nf", c, a) * lb)
    return np.arctan2(det, div).sum(1) / (2 * np.pi)


def _sample(mesh: trimesh.Trimesh, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) float64 area-weighted points on a mesh and their faces' unit normals."""
    face = rng.choice(len(mesh.faces), n, p=mesh.area_faces / mesh.area)
    r = rng.random((n, 2))
    flip = r.sum(1) > 1
    r[flip] = 1 - r[flip]
    t = mesh.triangles[face]
    return t[:, 0] + r[:, :1] * (t[:, 1] - t[:, 0]) + r[:, 1:] * (t[:, 2] - t[:, 0]), mesh.face_normals[face]


def _fewest(result: trimesh.Trimesh) -> int:
    """The fewest triangles that fill the flat regions of a closed mesh from their outlines, without new vertices:
    per region of n outline corners and h holes, n + 2 h - 2."""
    region, _ = flat_regions(np.asarray(result.vertices), np.asarray(result.faces))
    total = 0
    for r in np.unique(region):
        mine = result.faces[region == r]
        directed = np.concatenate([mine[:, [0, 1]], mine[:, [1, 2]], mine[:, [2, 0]]])
        keys = {tuple(e) for e in directed}
        border = [e for e in directed if (e[1], e[0]) not in keys]
        corners = len({int(a) for a, _ in border})
        graph = trimesh.graph.connected_components(np.array(border), min_len=1)
        total += corners + 2 * (len(graph) - 1) - 2
    return total


def _check(parts: list[trimesh.Trimesh], rng: np.random.Generator, groups: int = 1) -> trimesh.Trimesh:
    """The parts' union rebuilt: closed and outward, ``groups`` pieces, the fewest faces its flat regions'
    outlines need; on the true union both ways within 1e-8 of the prop's size (exact point-to-triangle distances:
    every point of it on a part's surface, every point of a part's surface with nothing just in front of it on
    it); no face hidden (just in front of every face lies outside every part, just behind inside one), and inside
    exactly where some part is (winding numbers at random points)."""
    vertices, faces = _joined(parts)
    norm = Normalization.fit(vertices)
    found = kitbash_union(norm.apply(vertices), faces)
    assert found is not None
    result = trimesh.Trimesh(norm.invert(found[0]), found[1], process=False)
    assert result.is_watertight and result.is_winding_consistent and result.volume > 0
    assert len(result.split(only_watertight=False)) == groups
    assert len(result.faces) == _fewest(result)
    size = 1.0 / norm.scale
    samples, normals = _sample(result, 4000, rng)
    assert distance_to_triangles(samples, vertices, faces).max() < 1e-8 * size
    assert not _inside_parts(samples + 1e-6 * size * normals, parts).any()
    assert _inside_parts(samples - 1e-6 * size * normals, parts).all()
    outside = [_sample(p, 2000, rng) for p in parts]
    outside = np.vstack([q[~_inside_parts(q + 1e-6 * size * n, parts)] for q, n in outside])
    assert distance_to_triangles(outside, result.vertices, result.faces).max() < 1e-8 * size
    probe = rng.uniform(vertices.min(0), vertices.max(0), (1500, 3))
    inside = _winding(norm.apply(probe), found[0], found[1]) > 0.5
    assert (inside == _inside_parts(probe, parts)).all()
    return result


@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e3])
def test_random_kitbashed_props_come_back_as_their_union(scale):
    """Eight random props per unit (millimetres to kilometres), any pose: each its boolean union, one piece."""
    rng = np.random.default_rng(int(scale * 1e3) % 9973)
    for _ in range(8):
        _check(_posed(_random_prop(rng), rng, scale), rng)


def _outside_points(parts: list[trimesh.Trimesh], n: int, rng: np.random.Generator
                    ) -> tuple[np.ndarray, np.ndarray]:
    """``n`` area-weighted points on the parts' surfaces with nothing just in front of them (what a scan of the
    prop sees: no face hidden inside another part) and their outward normals."""
    vertices, faces = _joined(parts)
    size = float(np.ptp(vertices, axis=0).max())
    points, normals = _sample(trimesh.Trimesh(vertices, faces, process=False), 3 * n, rng)
    seen = ~_inside_parts(points + 1e-6 * size * normals, parts)
    return points[seen][:n], normals[seen][:n]


def test_kitbashed_props_as_points_come_back_exact_or_not_at_all():
    """Sixteen random props as 8,192 oriented points of their outside, any pose, millimetres to kilometres: six or
    more rebuilt from their planes (the corners, else the cells of the arrangement), each one closed, outward and
    within the planes' tolerance of the true union both ways (where its points are: a face that none of them lies
    on is not there to rebuild).  A part's face too small for a plane of its own at that density (a step of a
    fraction of the points' spacing) leaves the rest to the networks."""
    rng = np.random.default_rng(4)
    rebuilt, tolerance = 0, PlanarConfig.tolerance
    for i in range(16):
        parts = _posed(_random_prop(rng), rng, (1e-3, 1.0, 1e3)[i % 3])
        points, normals = _outside_points(parts, 8192, rng)
        norm = Normalization.fit(points)
        unit = norm.apply(points)
        found = polyhedron(unit, normals) or plane_cells(unit, normals)
        if found is None:
            continue
        rebuilt += 1
        vertices, faces = _joined(parts)
        union = kitbash_union(norm.apply(vertices), faces)
        result = trimesh.Trimesh(*found, process=False)
        assert result.is_watertight and result.is_winding_consistent and result.volume > 0
        assert distance_to_triangles(result.sample(4000, seed=0), *union).max() < tolerance, i
        # The union where the points are: a part's face that none of them lies on is not there to rebuild.
        samples = trimesh.Trimesh(*union, process=False).sample(4000, seed=0)
        tree = cKDTree(unit)
        spacing = float(np.median(tree.query(unit, k=9)[0][:, 8]))
        samples = samples[tree.query(samples)[0] < 0.5 * spacing]
        assert distance_to_triangles(samples, *found).max() < tolerance, i
    assert rebuilt >= 6


def test_parts_that_touch_nothing_stay_apart():
    """A random prop and a box set apart from it: two pieces, the lone box as it was (its eight corners)."""
    rng = np.random.default_rng(5)
    for _ in range(3):
        prop = _random_prop(rng)
        lone = _box([3, 3, 3], [3.5, 3.2, 3.9])
        result = _check(prop + [lone], rng, groups=2)
        near = np.linalg.norm(result.vertices[:, None] - lone.vertices[None], axis=-1).min(0)
        assert near.max() < 1e-9


def test_the_kitbashed_chair_is_its_union_without_slivers():
    """The chair whose legs go 0.05 into its seat (72 faces): its union in 68 faces on 36 corners, every face on
    one of the six sides' directions (no pyramid), no angle under 1 degree (no sliver), no two vertices at one
    place."""
    rng = np.random.default_rng(0)
    result = _check(_chair(), rng)
    assert len(result.faces) == 68 and len(result.vertices) == 36
    normals = np.round(result.face_normals, 9)
    assert (np.abs(normals).max(1) == 1).all()  # axis-aligned faces only
    assert np.isclose(result.volume, 0.1 + 0.08 + 4 * 0.1 * 0.5 * 0.1)
    assert np.degrees(result.face_angles.min()) > 1.0
    corners = np.unique(np.round(result.vertices, 9), axis=0)
    assert len(corners) == len(result.vertices)


def test_single_open_separate_or_curved_inputs_are_not_kitbashed():
    """One closed part, an open part, parts that touch nothing, and two overlapping spheres (their union's flat
    regions are its hundreds of triangles): None (the planes path or the networks take them as they are)."""
    box = _box([0, 0, 0], [1, 2, 3])
    assert kitbash_union(*_joined([box])) is None
    assert kitbash_union(*_joined([box, _box([5, 5, 5], [6, 6, 6])])) is None
    opened = trimesh.Trimesh(box.vertices, box.faces[2:], process=False)
    assert kitbash_union(*_joined([opened, _box([0.5, 0.5, 0.5], [2, 2, 2])])) is None
    spheres = [trimesh.creation.icosphere(3), trimesh.creation.icosphere(3).apply_translation([1.2, 0, 0])]
    assert kitbash_union(*_joined(spheres)) is None


def test_the_pipeline_gives_a_kitbashed_chair_back_as_its_union():
    """The chair as an upload: rebuilt from its planes without running the networks, closed, one piece, fewer
    faces than its parts (68 of 72); as a dense mesh (each part subdivided: 1,152 faces) the same union."""
    pipe = Pipeline.random("tiny", seed=0)
    for dense in (False, True):
        parts = [p.subdivide().subdivide() if dense else p for p in _chair()]
        vertices, faces = _joined(parts)
        res = pipe.generate(Shape(vertices=vertices, faces=faces), GenerateParams(seed=0, max_vertices=24))
        assert res.info["result_from"] == "planes" and res.tokens == 0
        assert res.quality["watertight"] and res.quality["components"] == 1 and len(res.faces) == 68
        result = trimesh.Trimesh(res.vertices, res.faces, process=False)
        assert np.isclose(result.volume, 0.2)
