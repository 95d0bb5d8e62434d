"""A ladder of simple shapes whose artist vertices are known exactly.

Box, L-shaped block, box with a square through-hole, cylinder (16 sides), cone (16 sides),
icosphere (subdivisions 1 and 2) and torus (16 x 8 sections): the shapes a modeller builds in
a minute, each a closed mesh with the fewest vertices that describe it.  A vertex stage that
works must find these vertices (``benchmarks/primitives.py`` measures it).

The L and the holed box are prisms over a polygon (:func:`prism`) with their caps triangulated
by hand: trimesh's polygon extrusion needs shapely, which FastMesh does not depend on.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..shapes.io import sample_surface
from ..shapes.shape import Shape

SIDES = 16  # sections of the cylinder and the cone
N_POINTS = 8192  # points sampled on a primitive for the ladder's input


def prism(outline: np.ndarray, rings: list[list[int]], cap: np.ndarray, height: float) -> Shape:
    """Extrude a polygon (with holes) along +z into a closed mesh.

    Parameters
    ----------
    outline : (P, 2) float
        The polygon's corners (outer boundary and holes together).
    rings : list of int lists
        Each boundary as indices into ``outline``, walked with the solid on the left: the outer
        boundary counter-clockwise, holes clockwise (seen from +z).
    cap : (T, 3) int
        Triangles of the polygon, counter-clockwise seen from +z.
    height : float

    Returns
    -------
    Shape : 2P vertices (bottom at z = 0, then top), 2T + 2 * (ring edges) outward-facing faces.
    """
    p = len(outline)
    xy = np.asarray(outline, dtype=np.float64)
    vertices = np.concatenate([np.c_[xy, np.zeros(p)], np.c_[xy, np.full(p, float(height))]])
    cap = np.asarray(cap, dtype=np.int64)
    faces = [cap[:, ::-1], cap + p]  # bottom faces -z, top faces +z
    for ring in rings:
        a = np.asarray(ring, dtype=np.int64)
        b = np.roll(a, -1)
        faces += [np.c_[a, b, b + p], np.c_[a, b + p, a + p]]  # the wall of each edge, facing outwards
    return Shape(vertices=vertices, faces=np.concatenate(faces))


def _from_trimesh(mesh) -> Shape:
    return Shape(vertices=np.asarray(mesh.vertices, dtype=np.float64), faces=np.asarray(mesh.faces, dtype=np.int64))


def box() -> Shape:
    """Unit cube: 8 vertices, 12 faces."""
    import trimesh

    return _from_trimesh(trimesh.creation.box(extents=(1.0, 1.0, 1.0)))


def l_block() -> Shape:
    """An L-shaped block (a 1 x 1 square less a 0.5 x 0.5 corner, 0.4 high): 12 vertices."""
    outline = np.array([[0, 0], [1, 0], [1, 0.5], [0.5, 0.5], [0.5, 1], [0, 1]])
    cap = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 5], [3, 4, 5]])
    return prism(outline, [[0, 1, 2, 3, 4, 5]], cap, 0.4)


def holed_box() -> Shape:
    """A 1 x 1 x 0.4 box with a 0.4 x 0.4 square hole through it: 16 vertices."""
    outer = [[0, 0], [1, 0], [1, 1], [0, 1]]
    inner = [[0.3, 0.3], [0.7, 0.3], [0.7, 0.7], [0.3, 0.7]]
    # Each side of the frame between outer edge k and inner edge k: one quad, two triangles.
    cap = [t for k in range(4) for t in ([k, (k + 1) % 4, 4 + (k + 1) % 4], [k, 4 + (k + 1) % 4, 4 + k])]
    return prism(np.array(outer + inner, dtype=np.float64), [[0, 1, 2, 3], [4, 7, 6, 5]], np.array(cap), 0.4)


def cylinder() -> Shape:
    """Radius 0.5, height 1, 16 sides (trimesh's: with a centre vertex on each cap, 34 vertices)."""
    import trimesh

    return _from_trimesh(trimesh.creation.cylinder(radius=0.5, height=1.0, sections=SIDES))


def cone() -> Shape:
    """Radius 0.5, height 1, 16 sides (trimesh's: tip, base centre and rim, 18 vertices)."""
    import trimesh

    return _from_trimesh(trimesh.creation.cone(radius=0.5, height=1.0, sections=SIDES))


def icosphere(subdivisions: int) -> Shape:
    """Unit icosphere: 42 vertices at 1 subdivision, 162 at 2."""
    import trimesh

    return _from_trimesh(trimesh.creation.icosphere(subdivisions=subdivisions))


def torus() -> Shape:
    """Major radius 1, minor 0.3, 16 x 8 sections: 128 vertices."""
    import trimesh

    return _from_trimesh(trimesh.creation.torus(major_radius=1.0, minor_radius=0.3, major_sections=16,
                                                minor_sections=8))


# The ladder, simplest first.
LADDER: dict[str, Callable[[], Shape]] = {
    "box": box,
    "l_block": l_block,
    "holed_box": holed_box,
    "cylinder": cylinder,
    "cone": cone,
    "icosphere1": lambda: icosphere(1),
    "icosphere2": lambda: icosphere(2),
    "torus": torus,
}


def random_shape(kind: str, rng: np.random.Generator) -> Shape:
    """One shape of a family drawn at random: its proportions, and for prisms its outline.

    Parameters
    ----------
    kind : one of ``RANDOM_KINDS``: ``box`` (sides 0.2-1 each), ``l_block`` (a box less a corner box, both of
        random sides), ``prism`` (a convex polygon of 3-8 corners at random angles, extruded), ``cylinder``
        and ``cone`` (16 sides, radius and height at random; trimesh's, with cap centres); or of ``OPEN_KINDS``:
        ``tray`` (a box of random sides without its top), ``roof`` (a gable roof of random proportions, its
        ridge off centre, without its floor); or of ``ROUND_KINDS`` (:func:`_round_shape`); or of ``SHALLOW_KINDS``
        (:func:`_shallow_shape`)
    rng : numpy Generator

    Returns
    -------
    Shape : a mesh whose vertices are all its artist vertices, longest side about 1, at the origin; closed
    for ``RANDOM_KINDS``, open along one side of its box for ``OPEN_KINDS``; for ``ROUND_KINDS`` a closed
    curved surface of many faces, longest side 1, whose vertices are no artist's.
    """
    import trimesh

    if kind in OPEN_KINDS:
        return _open_shape(kind, rng)
    if kind in ROUND_KINDS:
        return _round_shape(kind, rng)
    if kind in SHALLOW_KINDS:
        return _shallow_shape(kind, rng)
    if kind == "box":
        return _from_trimesh(trimesh.creation.box(extents=rng.uniform(0.2, 1.0, 3)))
    if kind == "l_block":
        w, d = rng.uniform(0.4, 1.0, 2)
        cw, cd = w * rng.uniform(0.25, 0.75), d * rng.uniform(0.25, 0.75)  # the corner cut away
        outline = np.array([[0, 0], [w, 0], [w, d - cd], [w - cw, d - cd], [w - cw, d], [0, d]])
        cap = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 5], [3, 4, 5]])
        return prism(outline, [list(range(6))], cap, rng.uniform(0.2, 1.0))
    if kind == "prism":
        k = int(rng.integers(3, 9))
        # Corners on an ellipse, each moved off its even spacing by up to 0.6 of its share: convex, in order.
        angles = np.linspace(0, 2 * np.pi, k, endpoint=False) + rng.uniform(-0.6, 0.6, k) * np.pi / k
        angles += rng.uniform(0, 2 * np.pi)
        outline = 0.5 * np.c_[np.cos(angles), rng.uniform(0.4, 1.0) * np.sin(angles)]
        cap = np.array([[0, i, i + 1] for i in range(1, k - 1)])
        return prism(outline, [list(range(k))], cap, rng.uniform(0.2, 1.0))
    if kind == "cylinder":
        return _from_trimesh(trimesh.creation.cylinder(radius=rng.uniform(0.1, 0.5), height=rng.uniform(0.2, 1.0),
                                                       sections=SIDES))
    if kind == "cone":
        return _from_trimesh(trimesh.creation.cone(radius=rng.uniform(0.1, 0.5), height=rng.uniform(0.2, 1.0),
                                                   sections=SIDES))
    kinds = RANDOM_KINDS + OPEN_KINDS + ROUND_KINDS + SHALLOW_KINDS
    raise ValueError(f"unknown kind {kind!r}; one of {', '.join(kinds)}")


RANDOM_KINDS = ("box", "l_block", "prism", "cylinder", "cone")
OPEN_KINDS = ("tray", "roof")
ROUND_KINDS = ("capsule", "tube", "torus", "ellipsoid")
SHALLOW_KINDS = ("low_roof", "wedge")


def _shallow_shape(kind: str, rng: np.random.Generator) -> Shape:
    """A closed prism with two faces a few degrees from meeting flat or folding shut: a ``low_roof`` (a house of
    random proportions whose two roof slopes rise 1-5 degrees each, the ridge off centre: 10 corners) or a
    ``wedge`` (a ramp rising 2-10 degrees to a vertical back, 6 corners)."""
    w, d = rng.uniform(0.5, 1.0), rng.uniform(0.2, 1.0)
    if kind == "wedge":
        rise = w * np.tan(np.radians(rng.uniform(2.0, 10.0)))
        return prism(np.array([[0, 0], [w, 0], [w, rise]]), [[0, 1, 2]], np.array([[0, 1, 2]]), d)
    h, ridge = rng.uniform(0.2, 1.0), w * rng.uniform(0.3, 0.7)
    left, right = np.tan(np.radians(rng.uniform(1.0, 5.0, 2)))
    top = h + min(ridge * left, (w - ridge) * right)  # the lower slope sets the ridge; the other end its eave
    outline = np.array([[0, 0], [w, 0], [w, top - (w - ridge) * right], [ridge, top], [0, top - ridge * left]])
    return prism(outline, [list(range(5))], np.array([[0, 1, 2], [0, 2, 3], [0, 3, 4]]), d)


def _round_shape(kind: str, rng: np.random.Generator) -> Shape:
    """A closed curved mesh, scaled to a longest side of 1: a ``capsule`` (length 0.2-3, radius 0.1-0.8 before
    scaling; 4,096 faces), a ``tube`` (a pipe of 6-39 sides, its wall 0.05-0.5 thick around a hole of radius
    0.2-0.8, 0.1-3 long), a ``torus`` (tube radius 0.1-0.6 of its ring's, 12-63 x 8-31 sections) or an
    ``ellipsoid`` (radii 0.2-1 each, 1,280 faces)."""
    import trimesh

    if kind == "capsule":
        m = trimesh.creation.capsule(height=rng.uniform(0.2, 3.0), radius=rng.uniform(0.1, 0.8))
    elif kind == "tube":
        hole = rng.uniform(0.2, 0.8)
        m = trimesh.creation.annulus(hole, hole + rng.uniform(0.05, 0.5), rng.uniform(0.1, 3.0),
                                     sections=int(rng.integers(6, 40)))
    elif kind == "torus":
        ring = rng.uniform(0.5, 1.5)
        m = trimesh.creation.torus(ring, ring * rng.uniform(0.1, 0.6), int(rng.integers(12, 64)),
                                   int(rng.integers(8, 32)))
    else:
        m = trimesh.creation.icosphere(subdivisions=3)
        m.apply_scale(rng.uniform(0.2, 1.0, 3))
    m.apply_scale(1.0 / m.extents.max())
    return _from_trimesh(m)


def _open_shape(kind: str, rng: np.random.Generator) -> Shape:
    """A tray (8 corners, 10 triangles: a box without its +Y side) or a roof (6 corners, 2 gables and 2 slopes)."""
    import trimesh

    if kind == "tray":
        box = trimesh.creation.box(extents=rng.uniform(0.2, 1.0, 3))
        return Shape(vertices=np.asarray(box.vertices), faces=np.asarray(box.faces)[box.face_normals[:, 1] < 0.5])
    w, h, d = rng.uniform(0.2, 1.0, 3)
    ridge = rng.uniform(-0.3, 0.3) * w
    v = np.array([[-w / 2, 0, 0], [w / 2, 0, 0], [ridge, h, 0], [-w / 2, 0, d], [w / 2, 0, d], [ridge, h, d]])
    return Shape(vertices=v - v.mean(0), faces=np.array([[0, 2, 1], [3, 4, 5], [0, 3, 5], [0, 5, 2], [1, 2, 5],
                                                          [1, 5, 4]]))


def posed(shape: Shape, rng: np.random.Generator, turn: bool = True, millimetres: bool = False) -> Shape:
    """``shape`` turned at random (``turn``), and with ``millimetres`` scaled by 1,000 and moved up to 10 m
    from the origin, as a CAD export in millimetres would be."""
    import trimesh

    v = np.asarray(shape.vertices, dtype=np.float64)
    if turn:
        v = v @ trimesh.transformations.random_rotation_matrix(rng.random(3))[:3, :3].T
    if millimetres:
        v = v * 1000.0 + rng.uniform(-1e4, 1e4, 3)
    return Shape(vertices=v, faces=shape.faces)


def primitive(name: str) -> Shape:
    """The mesh of the ladder's shape ``name`` (one of ``LADDER``)."""
    if name not in LADDER:
        raise ValueError(f"unknown primitive {name!r}; one of {', '.join(LADDER)}")
    return LADDER[name]()


def point_cloud(mesh: Shape, n: int = N_POINTS, seed: int = 0) -> Shape:
    """``n`` area-weighted samples of ``mesh`` with their face normals, as a point-cloud Shape."""
    pts, nrm = sample_surface(mesh, n, seed=seed)
    return Shape(vertices=pts.astype(np.float64), normals=nrm.astype(np.float64))


# --------------------------------------------------------------------------- curved shapes, for face counts

CURVED_KINDS = ("sphere", "torus", "box", "bumpy")


def curved_shape(kind: str, rng: np.random.Generator) -> Shape:
    """A fine closed mesh of a family drawn at random, for face-count checks (``facecount``).

    Parameters
    ----------
    kind : one of ``CURVED_KINDS``: ``sphere`` (an ellipsoid of radii 0.2-0.5, 5,120 faces), ``torus`` (major
        radius 0.35, minor 0.05-0.15, 64 x 32 sections), ``box`` (sides 0.2-1, each face split into 64),
        ``bumpy`` (a sphere of 5,120 faces with up to three random lobes of +-20 % of its radius)
    rng : numpy Generator

    Returns
    -------
    Shape : about 1 across, at the origin.
    """
    import trimesh

    if kind == "sphere":
        m = trimesh.creation.icosphere(subdivisions=4)
        return Shape(vertices=np.asarray(m.vertices) * rng.uniform(0.2, 0.5, 3), faces=np.asarray(m.faces))
    if kind == "torus":
        return _from_trimesh(trimesh.creation.torus(major_radius=0.35, minor_radius=rng.uniform(0.05, 0.15),
                                                    major_sections=64, minor_sections=32))
    if kind == "box":
        m = trimesh.creation.box(extents=rng.uniform(0.2, 1.0, 3)).subdivide().subdivide().subdivide()
        return _from_trimesh(m)
    if kind == "bumpy":
        m = trimesh.creation.icosphere(subdivisions=4)
        v = np.asarray(m.vertices)
        lobes = rng.normal(size=(int(rng.integers(1, 4)), 3))
        lobes /= np.linalg.norm(lobes, axis=1, keepdims=True)
        radius = 1.0 + (rng.uniform(-0.2, 0.2, len(lobes)) * np.exp(4.0 * (v @ lobes.T - 1.0))).sum(1)
        return Shape(vertices=0.5 * v * radius[:, None], faces=np.asarray(m.faces))
    raise ValueError(f"unknown kind {kind!r}; one of {', '.join(CURVED_KINDS)}")


def coarse_copy(mesh: Shape, faces: int, rng: np.random.Generator, jitter: float = 0.005
                ) -> tuple[np.ndarray, np.ndarray]:
    """``mesh`` remade with about ``faces`` faces, its vertices moved at random by up to ``jitter`` of its
    size: a stand-in for a generated result, made by another decimator (``fast-simplification``'s) than
    ``facecount``'s and subdivided first where the mesh has fewer faces.

    Returns
    -------
    vertices : (V, 3) float64, faces : (F, 3) int64
    """
    import fast_simplification
    import trimesh

    v, f = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
    while len(f) < faces:
        v, f = trimesh.remesh.subdivide(v, f)
    if len(f) > faces:
        v, f = fast_simplification.simplify(v, f, target_count=int(faces))
    size = float(np.ptp(v, axis=0).max())
    return v + rng.uniform(-jitter, jitter, v.shape) * size, np.asarray(f, dtype=np.int64)


def curved_input(kind: str, given: str, rng: np.random.Generator) -> tuple[Shape, Shape]:
    """A :func:`curved_shape` turned at random, half the time in millimetres far from the origin, scaled by
    10^-2 to 10^2, and given as its mesh (``given`` "mesh") or as 2,000-20,000 of its points with normals of
    random sign (``given`` "points": as estimated normals may point).

    Returns
    -------
    mesh : Shape, the posed mesh; input : Shape, what the pipeline is given
    """
    mesh = posed(curved_shape(kind, rng), rng, turn=True, millimetres=bool(rng.random() < 0.5))
    mesh = Shape(vertices=mesh.vertices * 10 ** rng.uniform(-2, 2), faces=mesh.faces)
    if given == "mesh":
        return mesh, mesh
    if given != "points":
        raise ValueError(f"given must be mesh or points, got {given!r}")
    points = point_cloud(mesh, int(rng.integers(2000, 20000)), seed=int(rng.integers(1 << 16)))
    signs = rng.choice([-1.0, 1.0], (len(points.vertices), 1))
    return mesh, Shape(vertices=points.vertices, normals=points.normals * signs)
