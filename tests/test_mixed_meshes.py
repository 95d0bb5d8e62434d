"""Mixed mesh inputs: a box with round parts on it (a boss, a dome, a knob, a cone), dense as an export gives it,
simplified within its own surface (``fastmesh.faces.flat``): flat faces as their outlines, round parts within the
bound, no network run."""

import manifold3d
import numpy as np
import trimesh
from poses import posed, random_pose

from fastmesh.faces import flat
from fastmesh.faces.defects import winding
from fastmesh.faces.meshops import distance_to_triangles, edge_face_counts
from fastmesh.params import GenerateParams
from fastmesh.shapes.shape import Shape
from fastmesh.tokenizer.grid import CELL


def mixed_prop(rng: np.random.Generator) -> Shape:
    """A box of random sides with one or two round parts standing on its top, each a cylinder, a cone (24-96 sides)
    or a sphere half sunk into it, of random size and place: their union (manifold3d), closed and wound outward."""
    a, b, c = rng.uniform(0.4, 1.0, 3)
    solid = manifold3d.Manifold.cube([a, b, c], center=True)
    for _ in range(rng.integers(1, 3)):
        kind = rng.choice(["cylinder", "sphere", "cone"])
        r = rng.uniform(0.15, 0.45) * min(a, c)
        x, z = rng.uniform(-0.5, 0.5, 2) * [a - 2 * r, c - 2 * r]
        sides = int(rng.integers(24, 97))
        if kind == "sphere":
            part = manifold3d.Manifold.sphere(r, sides)
        else:  # standing up from just under the top
            part = manifold3d.Manifold.cylinder(rng.uniform(0.2, 0.6), r, r if kind == "cylinder" else 0.0, sides)
            part = part.rotate([-90, 0, 0]).translate([0, -0.01, 0])
        solid = solid + part.translate([x, b / 2, z])
    m = solid.to_mesh()
    return Shape(vertices=np.asarray(m.vert_properties[:, :3], dtype=np.float64),
                 faces=np.asarray(m.tri_verts, dtype=np.int64))


def dense(shape: Shape, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``shape`` split into faces of sides under 2.5-5 % of its size (10,000-60,000 faces), as a CAD export or a
    remesh gives it."""
    size = float(np.ptp(shape.vertices, axis=0).max())
    return trimesh.remesh.subdivide_to_size(shape.vertices, shape.faces, rng.uniform(0.025, 0.05) * size)


def both_ways(v: np.ndarray, f: np.ndarray, truth: Shape) -> float:
    """The largest exact distance between the mesh and ``truth``, both ways, over 4,000 samples of each."""
    sample = lambda a, b: trimesh.Trimesh(a, b, process=False).sample(4000, seed=0)  # noqa: E731
    return max(distance_to_triangles(sample(v, f), truth.vertices, truth.faces).max(),
               distance_to_triangles(sample(truth.vertices, truth.faces), v, f).max())


def test_a_mixed_prop_comes_back_simplified_within_its_surface_closed_and_wound_one_way():
    """Six random mixed props, any pose, mm to km, every other one stored inside out: each from its own surface (no
    network), closed, wound one way and outward, with fewer faces than the truth's own, within the flat path's gap
    (half a cell) of the truth both ways."""
    from fastmesh.pipeline import Pipeline

    pipe = Pipeline.random()
    rng = np.random.default_rng(12)
    for i in range(6):
        unit, pose = mixed_prop(rng), random_pose(rng)
        v, f = dense(unit, rng)
        f = f[:, ::-1] if i % 2 else f  # as a format that keeps its faces wound clockwise gives them
        truth = Shape(vertices=posed(unit.vertices, pose), faces=unit.faces)
        res = pipe.generate(Shape(vertices=posed(v, pose), faces=f), GenerateParams(seed=0))
        assert res.info["result_from"] == "simplified" and res.tokens == 0, i
        assert edge_face_counts(res.faces).min() == 2 and edge_face_counts(res.faces).max() == 2, i
        assert winding(res.vertices, res.faces)["misoriented_edges"] == 0, i
        assert trimesh.Trimesh(res.vertices, res.faces, process=False).volume > 0, i  # outward
        assert len(res.faces) < len(truth.faces), i
        size = float(np.ptp(truth.vertices, axis=0).max())
        assert both_ways(res.vertices, res.faces, truth) <= 0.5 * CELL * size, i


def test_a_result_that_strays_past_the_gap_is_made_again_at_a_tighter_bound():
    """At the rim of a boss the bound (a mean over the planes a collapse replaces, most of them the cap's) lets
    the surface leave the input by more than the gap: one try gives nothing, three a result within the gap."""
    rng = np.random.default_rng(3)
    strayed = 0
    for _ in range(6):
        unit = mixed_prop(rng)
        v, f = dense(unit, rng)
        v = (v - v.min(axis=0)) / np.ptp(v, axis=0).max()
        if flat.simplify_flat(v, f, flat.FlatConfig(tries=1)) is None:
            strayed += 1
            again = flat.simplify_flat(v, f)
            assert again is not None and flat._gap(v, f, *again) <= flat.FlatConfig().max_gap
    assert strayed >= 1


def test_pieces_stored_inside_out_are_turned_and_sheets_kept():
    """A box as it should be, one stored inside out, a box without its lid stored inside out (open, but it encloses
    a volume, as a body open at the neck does), a flat sheet and a box with one face wound against the rest: the
    three boxes come out outward; the sheet (it has no inside) and the box wound against itself as given."""
    from fastmesh.faces.orient import outward_pieces

    def box(k):
        b = trimesh.creation.box(extents=(1.0, 0.5, 0.3))
        return b.vertices + (3.0 * k, 0.0, 0.0), b.faces

    (a_v, a_f), (b_v, b_f), (c_v, c_f), (d_v, d_f) = (box(k) for k in range(4))
    lidless = c_f[np.asarray(trimesh.Trimesh(c_v, c_f).face_normals[:, 2] < 0.5)]
    sheet_v = np.array([[0.0, 3.0, 0.0], [1.0, 3.0, 0.0], [1.0, 4.0, 0.0], [0.0, 4.0, 0.0]])
    against = d_f.copy()
    against[0] = against[0, ::-1]
    v = np.vstack([a_v, b_v, c_v, d_v, sheet_v])
    f = np.vstack([a_f, b_f[:, ::-1] + 8, lidless[:, ::-1] + 16, against + 24, [[34, 33, 32], [35, 34, 32]]])
    out = outward_pieces(v, f)
    np.testing.assert_array_equal(out[:34], np.vstack([a_f, b_f + 8, lidless + 16]))
    np.testing.assert_array_equal(out[34:], f[34:])
