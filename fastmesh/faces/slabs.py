"""Sheets that stand for thin solid parts, made thin closed parts united with the solid.

A wing, a fin or a blade thinner than the decoded vertices can enclose comes back from the solid face stage as a
piece of the selection's mesh (``solid.lost_parts``): one sheet where the input has two sides, so that a renderer
shows the back of its faces from one side or the other.  Where the input's samples lie on both sides of such a
sheet, facing away from it (:func:`sides`), it becomes a slab between its copies moved to the samples of either
side and a wall along its rim (:func:`slab`), or where that slab would cross itself, one prism per face, the convex
hull of its six corners (:func:`prisms`: a valid solid whatever the sheet's folds); the slabs, the prisms and the
solid are made one by a boolean union (manifold3d: exact and robust where the parts overlap or pass into each
other, as a wing's root passes into a fuselage), closed, wound outward and free of self-intersections by
construction (:func:`thickened`).  A sheet whose samples
lie on one side (a true sheet) stays a sheet.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .meshops import crowded_edges, face_sides, open_sides, piece_labels, welded_in_place, wound_alike
from .orient import orient_faces

# A sample faces a side of the sheet where its normal is within this cosine of the sheet's normal, either way.
SIDE_COS = 0.5
# The samples read at each vertex: this many nearest, within ``reach`` (``thickened``).
SIDE_SAMPLES = 16
# A sheet is a slab where at least this share of its vertices sees samples on both of its sides.
BOTH_SIDES_SHARE = 0.5
# A piece of the union enclosing at most this share of its volume is a flat leftover of two prisms' shared wall
# (four faces, no volume), not a part.
FLAT_PIECE = 1e-9
# Where parts of the union touch along an edge only (four faces on it), the parts that may hold that edge go and
# the union is made again, at most this many times; then the thin parts are not united.
UNION_ROUNDS = 3


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(N, 3) unit normals of ``vertices`` (N, 3): the area-weighted sum of their ``faces``' (F, 3) normals
    (zero where a vertex has no face)."""
    t = vertices[faces]
    cross = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    n = np.zeros_like(vertices)
    for i in range(3):
        np.add.at(n, faces[:, i], cross)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, length, out=np.zeros_like(n), where=length > 0)


def sides(vertices: np.ndarray, normal: np.ndarray, points: np.ndarray, normals: np.ndarray, tree: cKDTree,
          reach: float) -> tuple[np.ndarray, np.ndarray]:
    """(N,) each, how far along ``normal`` (N, 3) from each of ``vertices`` (N, 3) the input's front and back lie:
    the median offset of the nearby samples (``points``, ``normals`` (P, 3); at most ``SIDE_SAMPLES`` within
    ``reach``) that face with the normal, and of those that face against it; NaN where there are none."""
    dist, idx = tree.query(vertices, k=SIDE_SAMPLES, distance_upper_bound=reach)
    near = np.isfinite(dist)
    idx = np.where(near, idx, 0)
    offset = np.einsum("nkj,nj->nk", points[idx] - vertices[:, None], normal)
    facing = np.einsum("nkj,nj->nk", normals[idx], normal)
    front = np.where(near & (facing > SIDE_COS), offset, np.nan)
    back = np.where(near & (facing < -SIDE_COS), offset, np.nan)
    return _median(front), _median(back)


def _median(values: np.ndarray) -> np.ndarray:
    """(N,) the median of each row of ``values`` (N, K) over its numbers; NaN for a row of none."""
    out = np.full(len(values), np.nan)
    has = np.isfinite(values).any(1)
    out[has] = np.nanmedian(values[has], axis=1)
    return out


def slab(vertices: np.ndarray, faces: np.ndarray, front: np.ndarray, back: np.ndarray
         ) -> tuple[np.ndarray, np.ndarray]:
    """A closed slab from a sheet: ``vertices`` (N, 3) of ``faces`` (F, 3) (wound alike, edge-manifold, open)
    moved by ``front`` (N, 3) for the copy that keeps the winding and ``back`` (N, 3) for the reversed copy, and a
    wall of two triangles along each open side.  Returns (2N, 3) vertices, the front copy's first, and faces."""
    n = len(vertices)
    s = face_sides(faces)[open_sides(faces)]
    a, b = s[:, 0], s[:, 1]
    # Each side a -> b of the front copy runs b -> a in its wall, and the back copy's a' <- b' runs a' -> b'.
    wall = np.concatenate([np.stack([b, a, a + n], 1), np.stack([b, a + n, b + n], 1)])
    f = np.concatenate([faces, faces[:, ::-1] + n, wall])
    return np.concatenate([vertices + front, vertices + back]), f


def prisms(vertices: np.ndarray, faces: np.ndarray, front: np.ndarray, back: np.ndarray) -> list:
    """One manifold3d solid per face of a sheet: the convex hull of its corners moved by ``front`` and by ``back``
    (N, 3), for ``vertices`` (N, 3) of ``faces`` (F, 3), with those six corners (6, 3); a face whose hull is flat
    gives none."""
    import manifold3d as mf

    top, bottom = vertices + front, vertices + back
    out = []
    for t in np.asarray(faces, dtype=np.int64).reshape(-1, 3):
        corners = np.concatenate([top[t], bottom[t]])
        hull = mf.Manifold.hull_points(np.ascontiguousarray(corners))
        if not hull.is_empty():
            out.append((hull, corners))
    return out


def thickened(vertices: np.ndarray, faces: np.ndarray, sheets: np.ndarray, points: np.ndarray,
              normals: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """The solid united with each piece of ``sheets`` that stands for a thin solid part.

    Parameters
    ----------
    vertices : (N, 3) float
    faces : (F, 3) int, the solid: closed and wound outward (or none)
    sheets : (G, 3) int, faces of ``vertices``: the pieces to read (those patched in)
    points, normals : (P, 3) float, the input's oriented samples
    reach : float, how far from a vertex its samples are read

    Returns
    -------
    vertices : (M, 3), those given, then the union's
    faces : (F', 3) int, the union of the solid and the thin parts (the solid as it came where there is none, or
        where it is no manifold3d solid)
    rest : (G', 3) int, the pieces of ``sheets`` that stay sheets
    made : int, how many pieces became thin parts
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    sheets = np.asarray(sheets, dtype=np.int64).reshape(-1, 3)
    pts, nrm = np.asarray(points, dtype=np.float64), np.asarray(normals, dtype=np.float64)
    tree = cKDTree(pts)
    label = piece_labels(sheets)
    solid = _manifold(v, f)
    pieces = [sheets[label == k] for k in range(int(label.max(initial=-1)) + 1)]
    parts = [] if solid is None else [(*p, k) for k, piece in enumerate(pieces)
                                      for p in _thin_part(v, piece, pts, nrm, tree, reach) or ()]
    united = _united(solid, parts) if parts else None
    if united is None:
        return v, f, sheets, 0
    # A piece none of whose parts the union kept stays a sheet.
    rest = [piece for k, piece in enumerate(pieces) if k not in united[2]]
    rest_f = np.concatenate([np.zeros((0, 3), dtype=np.int64), *rest])
    return np.concatenate([v, united[0]]), united[1] + len(v), rest_f, len(united[2])


def _united(solid, parts: list) -> tuple[np.ndarray, np.ndarray, set] | None:
    """The union of ``solid`` and the thin parts ``parts`` ((manifold, its vertices (C, 3), its piece) each: a
    slab or a prism) as vertices (M, 3) and faces (G, 3), edge-manifold once welded, and the pieces with a part in
    it: where two of its parts touch along an edge only (manifold3d keeps both pairs of faces on it, on two
    copies of its ends), the parts whose box holds that edge go and it is made again (``UNION_ROUNDS``).  None
    where it fails or an edge stays crowded."""
    import manifold3d as mf

    for _ in range(UNION_ROUNDS):
        union = mf.Manifold.batch_boolean([solid, *[p[0] for p in parts]], mf.OpType.Add)
        if union.status() != mf.Error.NoError:
            return None
        whole = union.volume()
        mesh = mf.Manifold.compose([p for p in union.decompose() if p.volume() > FLAT_PIECE * whole]).to_mesh64()
        out_v = np.asarray(mesh.vert_properties, dtype=np.float64)[:, :3]
        out_f = np.asarray(mesh.tri_verts, dtype=np.int64).reshape(-1, 3)
        # manifold3d keeps two copies of a vertex where parts touch along an edge: welded, that edge has four faces.
        welded_v, welded_f = welded_in_place(out_v, out_f)
        crowded = welded_v[crowded_edges(welded_f)]  # (K, 2, 3) the ends of each crowded edge
        if len(crowded) == 0:
            return out_v, out_f, {p[2] for p in parts}
        kept = [p for p in parts if not _near_edge(p[1], crowded)]
        if len(kept) == len(parts):
            return None
        parts = kept
    return None


def _near_edge(corners: np.ndarray, edges: np.ndarray) -> bool:
    """Whether the middle of one of ``edges`` (K, 2, 3) lies in the box of ``corners`` (C, 3), grown by a hair: the
    part those corners span may hold that edge (its own, or where the union cut it)."""
    middle = edges.mean(1)
    lo, hi = corners.min(0), corners.max(0)
    hair = 1e-9 * max(float(np.abs(corners).max()), 1.0)
    return bool(((middle >= lo - hair) & (middle <= hi + hair)).all(1).any())


def _manifold(vertices: np.ndarray, faces: np.ndarray):
    """``faces`` (F, 3) of ``vertices`` as a manifold3d solid (an empty one for no faces); None where they are no
    valid solid (open, an edge of three faces)."""
    import manifold3d as mf

    if len(faces) == 0:
        return mf.Manifold()
    used, local = np.unique(faces, return_inverse=True)
    solid = mf.Manifold(mf.Mesh64(vert_properties=np.ascontiguousarray(vertices[used]),
                                  tri_verts=np.ascontiguousarray(local.reshape(-1, 3).astype(np.uint64))))
    return solid if solid.status() == mf.Error.NoError else None


def _thin_part(vertices: np.ndarray, piece: np.ndarray, points: np.ndarray, normals: np.ndarray, tree: cKDTree,
               reach: float) -> list | None:
    """The thin part of one open, edge-manifold ``piece`` (G, 3) of ``vertices`` between the input's two sides: its
    slab as one solid (:func:`_slab_solid`), else its prisms (:func:`prisms`); None where it is not a sheet wound
    alike or too few of its vertices see the input on both of its sides (:data:`BOTH_SIDES_SHARE`)."""
    used, local = np.unique(piece, return_inverse=True)
    f = orient_faces(vertices[used], local.reshape(-1, 3), outward=False)
    if not open_sides(f).any() or not wound_alike(f):
        return None
    v = vertices[used]
    normal = vertex_normals(v, f)
    front, back = sides(v, normal, points, normals, tree, reach)
    both = np.isfinite(front) & np.isfinite(back) & (front > back)
    if both.mean() < BOTH_SIDES_SHARE:
        return None
    # A vertex that sees one side only takes the piece's usual offset for the other.
    front = np.where(both, front, np.median(front[both]))[:, None] * normal
    back = np.where(both, back, np.median(back[both]))[:, None] * normal
    return _slab_solid(v, f, front, back) or prisms(v, f, front, back) or None


def _slab_solid(vertices: np.ndarray, faces: np.ndarray, front: np.ndarray, back: np.ndarray) -> list:
    """The :func:`slab` of a sheet as one manifold3d solid with its vertices (in a list, as :func:`prisms` gives
    its parts), where it crosses nothing of its own and is a valid solid (a sheet folded so that its copies or
    walls cross, or pinched at a vertex, is not: its prisms are); else an empty list.  One slab has about half the
    faces of its prisms' union, whose walls between neighbours need not meet exactly."""
    import manifold3d as mf

    from .crossings import crossing_faces

    sv, sf = slab(vertices, faces, front, back)
    if crossing_faces(sv, sf).any():
        return []
    made = mf.Manifold(mf.Mesh64(vert_properties=np.ascontiguousarray(sv),
                                 tri_verts=np.ascontiguousarray(sf.astype(np.uint64))))
    if made.status() != mf.Error.NoError or made.is_empty() or made.volume() <= 0:
        return []
    return [(made, sv)]
