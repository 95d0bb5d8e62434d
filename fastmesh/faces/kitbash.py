"""Kitbashed mesh inputs: closed parts that touch, overlap or pass into each other made one closed mesh, their
union, rebuilt from its planes.

Artists build props from parts: a chair of six boxes whose legs go a little into the seat, a tank from a hull and
a turret.  Each part is closed, but together they are no surface: faces hidden inside other parts, edges where
parts cross with no vertex.  :func:`kitbash_union` splits a mesh into its welded parts and, where some of them
touch or overlap, takes their union with manifold3d (exact, robust booleans: coincident faces, edges and corners
are decided consistently), so only the outside remains; parts that touch nothing stay as they are.  The union's
triangles are then merged into its flat regions (faces that lie in one plane, side by side) and each region is
triangulated again from its outline (``planar._triangulate``), the vertices along a straight edge between two
regions dropped: a box from two boxes side by side has 12 triangles, not the boolean's 20.
"""

from __future__ import annotations

import numpy as np

from ..shapes.arrangement import merge_points
from ..shapes.planar import _closed, _triangulate
from .meshops import distinct_corners, face_sides, open_sides, triangle_areas, weld, wound_alike

MAX_FACES = 500_000  # a denser mesh is a scan or a sculpt, not parts an artist placed (and its union takes seconds)
MAX_PARTS = 256  # more welded pieces than this are scattered debris or a particle mesh, not parts of a prop
# Each part is grown by this much (unit frame) before the union and the union shrunk back after: parts that touch
# face to face, their corners rounded differently once turned, then overlap and merge, where at 1e-16 apart the
# boolean would keep a crack of no width between them (a hidden wall).  It is also manifold3d's tolerance: edges
# shorter than it collapse, faces coplanar within it merge.
OVERLAP = 1e-9
MERGE = 1e-8  # corners of the shrunk union this close are one (the parts' own smallest edges are far longer)
MAX_PART_PLANES = 64  # a part of more flat regions is curved (a ball), not a flat part (a 62-sided cylinder is one)
MAX_REGIONS = 256  # a union of more flat regions has curved parts (two spheres of 320 faces: over 600)
# A face lies in a region's plane where its corners are within this of it (unit frame: the input's longest side 1).
# The boolean's intersection points are exact to about 1e-15; this leaves room for the parts' own float32 corners.
COPLANAR = 1e-7
STRAIGHT_SINE = 1e-9  # a boundary vertex whose two edges turn by less than this sine lies on a straight edge


def kitbash_union(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The union of a mesh's closed parts, rebuilt from its flat regions, where some of its parts touch or overlap.

    Parameters
    ----------
    vertices : (N, 3) float, in the unit frame (``shape.Normalization``)
    faces : (F, 3) int

    Returns
    -------
    (V, 3) float64 vertices and (G, 3) int64 faces, at most F, closed, edge-manifold and oriented outward: one
    piece per group of touching parts (the boolean's own triangles where its regions' outlines touch themselves);
    or None where the mesh has one part, a part that is not closed or is curved, no two parts that touch, or the
    union has more than ``MAX_REGIONS`` flat regions (the networks make those).
    """
    union = boolean_union(vertices, faces)[0]
    if union is None:
        return None
    found = flat_regions(*union, limit=MAX_REGIONS)
    if found is None:
        return None
    region, planes = found
    union = onto_planes(*union, region, planes), union[1]
    rebuilt = flat_rebuild(*union, region, planes)
    return union if rebuilt is None or len(rebuilt[1]) > len(union[1]) else rebuilt


def onto_planes(vertices: np.ndarray, faces: np.ndarray, region: np.ndarray, planes: np.ndarray) -> np.ndarray:
    """(N, 3) the vertices of a mesh moved the least onto the planes of the regions they belong to (``region``
    (F,), ``planes`` (R, 4), whose offsets are set here to the median over their vertices): the shrunk union's
    merged corners lie up to ``OVERLAP`` off, and a corner off its line by that would count as one."""
    pairs = np.unique(np.c_[faces.ravel(), np.repeat(region, 3)], axis=0)  # each vertex's regions, once each
    at, r = pairs[:, 0], pairs[:, 1]
    off = np.einsum("ij,ij->i", vertices[at], planes[r, :3])
    order = np.argsort(r, kind="stable")
    start = np.r_[0, np.flatnonzero(np.diff(r[order])) + 1]
    planes[:, 3] = np.array([np.median(chunk) for chunk in np.split(off[order], start[1:])])
    n = planes[r, :3]
    quad, rhs = np.zeros((len(vertices), 3, 3)), np.zeros((len(vertices), 3))
    np.add.at(quad, at, n[:, :, None] * n[:, None, :])
    np.add.at(rhs, at, n * (planes[r, 3] - off)[:, None])
    return vertices + np.einsum("nij,nj->ni", np.linalg.pinv(quad, rcond=1e-6, hermitian=True), rhs)


def boolean_union(vertices: np.ndarray, faces: np.ndarray) -> tuple[tuple[np.ndarray, np.ndarray] | None, int]:
    """The union of a mesh's welded parts (manifold3d's, of the parts grown by ``OVERLAP``, shrunk back:
    :func:`_shrunk`) as (V, 3) float64 vertices and (G, 3) int64 faces, and how many parts the mesh has.  The
    union is None where the parts are fewer than two or more than ``MAX_PARTS``, one is not closed or not flat
    (more than ``MAX_PART_PLANES`` flat regions), no two of them touch (the union has as many pieces as the
    mesh), or the mesh has more than ``MAX_FACES`` faces."""
    import manifold3d as mf

    if len(faces) > MAX_FACES:
        return None, 0
    v, f = weld(vertices, faces)
    if len(f) == 0:
        return None, 0
    label = parts(f)
    count = int(label.max()) + 1
    if not 2 <= count <= MAX_PARTS:
        return None, count
    solids = []
    for k in range(count):
        mine = f[label == k]
        if not _closed(mine) or flat_regions(v, mine, limit=MAX_PART_PLANES) is None:
            return None, count
        if _signed_volume(v, mine) < 0:  # wound inside out: the boolean reads it as a hole
            mine = mine[:, ::-1]
        used, local = np.unique(mine, return_inverse=True)
        local = local.reshape(-1, 3)
        solid = mf.Manifold(mf.Mesh64(vert_properties=np.ascontiguousarray(offset(v[used], local, OVERLAP)),
                                      tri_verts=np.ascontiguousarray(local.astype(np.uint64)), tolerance=OVERLAP))
        if solid.status() != mf.Error.NoError or solid.is_empty():
            return None, count
        solids.append(solid)
    union = mf.Manifold.batch_boolean(solids, mf.OpType.Add)
    if union.status() != mf.Error.NoError or union.is_empty() or len(union.decompose()) >= count:
        return None, count
    mesh = union.to_mesh64()
    grown = np.asarray(mesh.tri_verts, dtype=np.int64).reshape(-1, 3)
    return _shrunk(np.asarray(mesh.vert_properties, dtype=np.float64)[:, :3], grown), count


def _shrunk(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The union of the grown parts shrunk back by ``OVERLAP``: where a part's face lay in the plane of another's
    facing it, the growth left steps and strips 2 ``OVERLAP`` wide, which shrinking makes of no width; their
    corners (within ``MERGE`` of each other) made one vertex and their faces (now with a repeated corner, or two
    on the same corners) dropped.  None where that leaves no closed mesh."""
    v, index = merge_points(offset(vertices, faces, -OVERLAP), MERGE)
    f = index[faces]
    f = f[distinct_corners(f)]
    # Two faces on the same three corners (a strip's two sides, once it has no width) face each other: both go.
    same = np.unique(np.sort(f, axis=1), axis=0, return_inverse=True, return_counts=True)
    f = f[same[2][same[1].reshape(-1)] == 1]
    return (v, f) if len(f) and _closed(f) else None


def offset(vertices: np.ndarray, faces: np.ndarray, distance: float) -> np.ndarray:
    """(N, 3) the vertices of a closed mesh moved so that each of its faces' planes moves ``distance`` along its
    normal (out where positive): each vertex by the least-squares (least-norm) solution of n . x = distance over
    the normals of its faces, exact where they are three planes or fewer (a box's corner, an edge, a face)."""
    tri = vertices[faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = np.linalg.norm(normal, axis=1)
    unit = normal / np.maximum(area, 1e-300)[:, None]
    quad, rhs = np.zeros((len(vertices), 3, 3)), np.zeros((len(vertices), 3))
    for k in range(3):  # weighted by area: a sliver's normal is noise
        np.add.at(quad, faces[:, k], unit[:, :, None] * normal[:, None, :])
        np.add.at(rhs, faces[:, k], normal * distance)
    return vertices + np.einsum("nij,nj->ni", np.linalg.pinv(quad, rcond=1e-6, hermitian=True), rhs)


def parts(faces: np.ndarray) -> np.ndarray:
    """(F,) the part of each face of a welded mesh, 0 .. P - 1: faces joined across edges that exactly two faces
    share.  Parts that meet at an edge (a chair's back flush with its seat's rim: four faces there) or a corner
    share vertices once welded, yet stay two parts."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    e = np.sort(np.stack([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]], axis=1), axis=2).reshape(-1, 2)
    edge, count = np.unique(e, axis=0, return_inverse=True, return_counts=True)[1:]
    edge = edge.reshape(-1)
    order = np.argsort(edge, kind="stable")
    owner = order // 3
    pair = count[edge[order]] == 2
    first = pair & np.r_[True, edge[order][1:] != edge[order][:-1]]  # the first of each two-face edge's two uses
    a = owner[np.flatnonzero(first)]
    b = owner[np.flatnonzero(first) + 1]
    graph = coo_matrix((np.ones(len(a), dtype=np.int8), (a, b)), shape=(len(faces),) * 2)
    return connected_components(graph, directed=False)[1].astype(np.int64)


def _signed_volume(v: np.ndarray, f: np.ndarray) -> float:
    return float(np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6.0)


def flat_regions(vertices: np.ndarray, faces: np.ndarray, limit: int | None = None
                 ) -> tuple[np.ndarray, np.ndarray] | None:
    """The flat regions of a mesh: faces joined edge to edge that lie in one plane (within ``COPLANAR``
    of the plane of the region's largest face), whichever way they face: two faces in one plane that meet at an
    edge facing each other are a fold of no volume (where two parts' sides lay in one plane, their growth and
    shrinking leave one, or a needle without area), which the region's outline then leaves out.

    Returns
    -------
    region : (F,) int64, the region of each face, 0 .. R - 1
    planes : (R, 4) float64, each region's plane (unit normal n pointing out, offset d: n.x = d)
    or None where the regions are more than ``limit`` (found out as soon as they are: a curved mesh of a
    million faces is not walked through).
    """
    tri = vertices[faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = np.linalg.norm(normal, axis=1)
    unit = normal / np.maximum(area, 1e-300)[:, None]
    e = np.sort(np.stack([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]], axis=1), axis=2).reshape(-1, 2)
    edge = np.unique(e, axis=0, return_inverse=True)[1].reshape(-1)
    order = np.argsort(edge, kind="stable")
    ends = edge[order]
    pair = np.flatnonzero(ends[1:] == ends[:-1])  # an edge's two faces side by side (an open edge has one)
    across: list[list[int]] = [[] for _ in faces]
    for a, b in zip(order[pair] // 3, order[pair + 1] // 3, strict=True):
        across[a].append(int(b))
        across[b].append(int(a))
    region, planes = np.full(len(faces), -1), []
    for seed in np.argsort(-area):
        if region[seed] >= 0:
            continue
        if limit is not None and len(planes) == limit:
            return None
        n, d = unit[seed], float(unit[seed] @ tri[seed, 0])
        region[seed], stack = len(planes), [int(seed)]
        while stack:
            for g in across[stack.pop()]:
                if region[g] < 0 and np.abs(tri[g] @ n - d).max() < COPLANAR:
                    region[g] = len(planes)
                    stack.append(g)
        planes.append(np.r_[n, d])
    return region.astype(np.int64), np.array(planes)


def flat_rebuild(vertices: np.ndarray, faces: np.ndarray, region: np.ndarray, planes: np.ndarray,
                 straight: float = STRAIGHT_SINE) -> tuple[np.ndarray, np.ndarray] | None:
    """A mesh's flat regions (``region`` (F,), ``planes`` (R, 4): :func:`flat_regions`) each triangulated again
    from its outline, the vertices inside a region or along a straight edge between two regions (turning by a sine
    under ``straight``) dropped; None where the result is not as closed as the mesh (closed, or open along the same
    length of edges, each in one face; the mesh as it is then stands)."""
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    side = np.tile(region, 3)
    n = len(vertices)
    order = np.argsort(directed[:, 0] * n + directed[:, 1])
    keys = directed[order, 0] * n + directed[order, 1]
    found = np.minimum(np.searchsorted(keys, directed[:, 1] * n + directed[:, 0]), len(keys) - 1)
    twin = order[found]
    lone = keys[found] != directed[:, 1] * n + directed[:, 0]  # an open edge: the outline of its region
    out = lone | (side[twin] != side)
    border, owner = directed[out], side[out]
    keep = _corners(vertices, border, straight)
    loops = []
    for r, mine in zip(*_split_by(owner, border), strict=True):
        loops.extend((r, ring[keep[ring]]) for ring in _rings(mine, vertices, planes[r, :3]))
    if any(len(ring) < 3 for _, ring in loops):
        return None
    used = np.unique(np.concatenate([ring for _, ring in loops]))
    index = np.full(len(vertices), -1)
    index[used] = np.arange(len(used))
    out = _triangulate(vertices[used], planes, [(r, index[ring]) for r, ring in loops], COPLANAR)
    if out is None or not _as_closed(vertices[used], out, _open_length(vertices, directed[lone])):
        return None
    return vertices[used], fatter(vertices[used], out)


def _open_length(vertices: np.ndarray, edges: np.ndarray) -> float:
    """The total length of edges (E, 2)."""
    return float(np.linalg.norm(vertices[edges[:, 1]] - vertices[edges[:, 0]], axis=1).sum())


def _as_closed(vertices: np.ndarray, faces: np.ndarray, open_length: float) -> bool:
    """Whether a rebuild is closed (``open_length`` 0), or wound alike with every edge in at most two faces and its
    open edges as long as ``open_length`` (the mesh's own, whose straight runs it keeps)."""
    if open_length == 0.0:
        return _closed(faces)
    if not wound_alike(faces):
        return False
    length = _open_length(vertices, face_sides(faces)[open_sides(faces)])
    return abs(length - open_length) <= 1e-9 * max(open_length, 1.0)


def fatter(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``faces`` with edges inside flat regions turned where that widens the thinner of their two triangles.

    Ear clipping fills an outline with whatever ears come first: slivers across an L-shaped side, and caps (a
    triangle whose corner lies on its opposite edge, where an outline passes straight through a corner of a
    region beside it).  An edge between two triangles in one plane (within ``COPLANAR``) is turned to the other
    diagonal of their quadrilateral where both new triangles keep the orientation and the smallest angle of the
    two grows (Lawson's flips, as a Delaunay triangulation is made): the outline and the vertices stay.
    """
    f = faces.copy()
    for _ in range(len(f)):
        flips = _flips(vertices, f)
        if not flips:
            break
        touched: set[int] = set()
        for _, i, j, new_i, new_j in sorted(flips, reverse=True):  # the largest gains first, each face once
            if i not in touched and j not in touched:
                f[i], f[j] = new_i, new_j
                touched |= {i, j}
    return f


def _flips(vertices: np.ndarray, f: np.ndarray) -> list[tuple[float, int, int, tuple, tuple]]:
    """The flips of :func:`fatter`: (gain in the smallest angle, the two faces, their new corners)."""
    directed = {(int(f[i, k]), int(f[i, (k + 1) % 3])): (i, k) for i in range(len(f)) for k in range(3)}
    angle = _min_angles(vertices, f)
    out = []
    for (a, b), (i, k) in directed.items():
        if a > b or (b, a) not in directed:
            continue
        j, m = directed[(b, a)]
        c, d = int(f[i, (k + 2) % 3]), int(f[j, (m + 2) % 3])
        if c == d or (c, d) in directed or (d, c) in directed:
            continue
        quad = vertices[[a, b, c, d]]
        area = triangle_areas(vertices, f[[i, j]])
        big = vertices[f[i]] if area[0] >= area[1] else vertices[f[j]]
        normal = np.cross(big[1] - big[0], big[2] - big[0])
        normal /= np.linalg.norm(normal)
        if np.abs((quad - big[0]) @ normal).max() > COPLANAR:
            continue
        new_i, new_j = (a, d, c), (d, b, c)
        tri = vertices[[new_i, new_j]]
        turn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]) @ normal
        if (turn <= 0).any():
            continue
        now = min(angle[i], angle[j])
        after = _min_angles(vertices, np.array([new_i, new_j])).min()
        if after - now > 1e-9:
            out.append((float(after - now), i, j, new_i, new_j))
    return out


def _min_angles(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F,) each triangle's smallest angle in radians (0 for one without area)."""
    t = vertices[faces]
    out = np.full(len(faces), np.pi)
    for k in range(3):
        u, w = t[:, (k + 1) % 3] - t[:, k], t[:, (k + 2) % 3] - t[:, k]
        cos = np.einsum("ij,ij->i", u, w) / np.maximum(np.linalg.norm(u, axis=1) * np.linalg.norm(w, axis=1), 1e-300)
        out = np.minimum(out, np.arccos(np.clip(cos, -1, 1)))
    return out


def _corners(vertices: np.ndarray, border: np.ndarray, straight: float = STRAIGHT_SINE) -> np.ndarray:
    """(V,) bool: the vertices an outline needs.  A vertex on the border between regions is needed unless it
    has two border neighbours in a straight line with it (it then lies inside one straight edge of both regions
    beside it, and both drop it)."""
    pairs = np.unique(np.sort(border, axis=1), axis=0)
    degree = np.bincount(pairs.ravel(), minlength=len(vertices))
    keep = degree > 0
    two = np.flatnonzero(degree == 2)
    if len(two):
        ends = np.concatenate([pairs, pairs[:, ::-1]])
        ends = ends[degree[ends[:, 0]] == 2]
        ends = ends[np.argsort(ends[:, 0], kind="stable")]
        mid, a, b = ends[0::2, 0], ends[0::2, 1], ends[1::2, 1]
        d1, d2 = vertices[a] - vertices[mid], vertices[b] - vertices[mid]
        sine = np.linalg.norm(np.cross(d1, d2), axis=1) / np.maximum(
            np.linalg.norm(d1, axis=1) * np.linalg.norm(d2, axis=1), 1e-300)
        on_line = (sine < straight) & (np.einsum("ij,ij->i", d1, d2) < 0)
        keep[mid[on_line]] = False
    return keep


def _split_by(label: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """The distinct ``label`` values (E,) and, for each, the ``rows`` (E, ...) that carry it."""
    order = np.argsort(label, kind="stable")
    values, start = np.unique(label[order], return_index=True)
    return values, np.split(rows[order], start[1:])


def _rings(edges: np.ndarray, vertices: np.ndarray, normal: np.ndarray) -> list[np.ndarray]:
    """Directed boundary edges (E, 2) of one region (its interior on their left seen along ``normal`` (3,))
    chained into rings of vertex ids.  Where the region touches itself at a vertex (two edges leave it), a ring
    arriving from u leaves by the edge that turns least clockwise from the way back to u: it keeps to its own
    wedge of the region, so the rings touch there without crossing."""
    leaving: dict[int, list[int]] = {}
    for a, b in edges:
        leaving.setdefault(int(a), []).append(int(b))
    rings = []
    while leaving:
        start = next(iter(leaving))
        ring, prev, a = [], None, start
        while a in leaving:
            ring.append(a)
            ways = leaving[a]
            b = ways[0] if len(ways) == 1 or prev is None else min(
                ways, key=lambda w: _clockwise(vertices[prev] - vertices[a], vertices[w] - vertices[a], normal))
            ways.remove(b)
            if not ways:
                del leaving[a]
            prev, a = a, b
            if a == start:
                break
        rings.append(np.array(ring, dtype=np.int64))
    return rings


def _clockwise(back: np.ndarray, out: np.ndarray, normal: np.ndarray) -> float:
    """The angle (0 .. 2 pi) from ``back`` to ``out`` turning clockwise seen along ``normal``."""
    angle = np.arctan2(np.cross(back, out) @ normal, back @ out)  # counter-clockwise, -pi .. pi
    return float((-angle) % (2 * np.pi))
