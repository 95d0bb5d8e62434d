"""Sheets that stand for thin solid parts, made thin closed parts (slabs).

A wing, a fin or a blade thinner than the decoded vertices can enclose comes back from the solid face stage as a
piece of the selection's mesh (``solid.lost_parts``): one sheet where the input has two sides, so that a renderer
shows the back of its faces from one side or the other.  Where the input's samples lie on both sides of such a
sheet, facing away from it (:func:`sides`), the sheet is made a slab: a copy on each side at the distance of that
side's samples, wound outward, and a wall along its rim (:func:`slab`).  The slab is closed and wound one way; it
comes back only where it crosses nothing (:func:`thickened`).  A sheet whose samples lie on one side (a true
sheet) stays a sheet.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .meshops import edge_face_counts, face_sides, open_sides, piece_labels, welded_fins, wound_alike
from .orient import orient_faces

# A sample faces a side of the sheet where its normal is within this cosine of the sheet's normal, either way.
SIDE_COS = 0.5
# The samples read at each vertex: this many nearest, within ``reach`` (``thickened``).
SIDE_SAMPLES = 16
# A sheet is a slab where at least this share of its vertices sees samples on both of its sides.
BOTH_SIDES_SHARE = 0.5


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


def thickened(vertices: np.ndarray, faces: np.ndarray, sheets: np.ndarray, points: np.ndarray,
              normals: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray, int]:
    """The mesh with each piece of ``sheets`` that stands for a thin solid part made a slab.

    Parameters
    ----------
    vertices : (N, 3) float
    faces : (F, 3) int, the mesh the slabs must not cross (the solid)
    sheets : (G, 3) int, faces of ``vertices``: the pieces to read (those patched in)
    points, normals : (P, 3) float, the input's oriented samples
    reach : float, how far from a vertex its samples are read

    Returns
    -------
    vertices : (M, 3), those given and the slabs' own
    faces : (F + G', 3), ``faces``, then each piece of ``sheets`` as it came or as its slab
    slabs : int, how many pieces became slabs
    """
    v = np.asarray(vertices, dtype=np.float64)
    pts, nrm = np.asarray(points, dtype=np.float64), np.asarray(normals, dtype=np.float64)
    tree = cKDTree(pts)
    label = piece_labels(sheets)
    # Each piece as it stands (a sheet, or its slab once made) and the vertices the slabs add after ``v``.
    pieces = [sheets[label == k] for k in range(int(label.max(initial=-1)) + 1)]
    added, made = [np.zeros((0, 3))], 0
    for k, piece in enumerate(pieces):
        made_slab = _slab_of(v, piece, pts, nrm, tree, reach)
        if made_slab is None:
            continue
        sv, sf = made_slab
        all_v = np.concatenate([v, *added])
        others = np.concatenate([faces, *pieces[:k], *pieces[k + 1:]]).astype(np.int64).reshape(-1, 3)
        if not _crosses(all_v, others, (sv, sf)):
            pieces[k] = sf + len(all_v)
            added.append(sv)
            made += 1
    out_f = np.concatenate([np.asarray(faces, dtype=np.int64).reshape(-1, 3), *pieces]).astype(np.int64)
    return np.concatenate([v, *added]), out_f.reshape(-1, 3), made


def _slab_of(vertices: np.ndarray, piece: np.ndarray, points: np.ndarray, normals: np.ndarray, tree: cKDTree,
             reach: float) -> tuple[np.ndarray, np.ndarray] | None:
    """The slab of one open, edge-manifold ``piece`` (G, 3) of ``vertices``, or None where it is not a sheet
    wound alike or too few of its vertices see the input on both of its sides (:data:`BOTH_SIDES_SHARE`)."""
    used, local = np.unique(piece, return_inverse=True)
    f = orient_faces(vertices[used], local.reshape(-1, 3), outward=False)
    if edge_face_counts(f).max(initial=0) > 2 or not open_sides(f).any() or not wound_alike(f):
        return None
    v = vertices[used]
    normal = vertex_normals(v, f)
    front, back = sides(v, normal, points, normals, tree, reach)
    both = np.isfinite(front) & np.isfinite(back) & (front > back)
    if both.mean() < BOTH_SIDES_SHARE:
        return None
    # A vertex that sees one side only takes the piece's usual offset for the other.
    front = np.where(both, front, np.median(front[both]))
    back = np.where(both, back, np.median(back[both]))
    return slab(v, f, front[:, None] * normal, back[:, None] * normal)


def _crosses(vertices: np.ndarray, faces: np.ndarray, made: tuple[np.ndarray, np.ndarray]) -> bool:
    """Whether the slab ``made`` (vertices, faces) crosses itself or any of ``faces`` of ``vertices``, or puts a
    third face on a side once welded (``meshops.welded_fins``: a rim vertex left where another part's is)."""
    from .crossings import crossing_faces

    sv, sf = made
    all_v, all_f = np.concatenate([vertices, sv]), np.concatenate([faces, sf + len(vertices)])
    mine = np.r_[np.zeros(len(faces), dtype=bool), np.ones(len(sf), dtype=bool)]
    return bool(welded_fins(all_v, all_f)[mine].any() or crossing_faces(all_v, all_f, among=mine).any())
