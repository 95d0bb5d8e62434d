"""A face count that holds: a result brought to the ``target_faces`` asked for.

The vertex decoder makes the count it chooses (a decoder trained to read the count follows it loosely and
breaks far from its own: ``SamplingConfig.read_count``; and its vertex limit caps what it can make: 1,000
vertices are about 2,000 faces).  :func:`hold_count` brings the result it made to the target when it is off
by more than ``KEEP``:

- too many faces: half-edge collapses of least quadric error (:func:`decimate`); each keeps one of its
  two vertices where it is, so the vertices stay the model's, and each must keep the surface a surface
  (``simplify``'s link condition, no fold-over, no face twice): a closed, edge-manifold result stays so;
- too few: the longest edges split at their middles (:func:`split_longest`), the new vertices moved onto
  the input surface (the tangent planes of the nearest input samples); a split changes no edge's
  neighbourhood, so the result keeps its topology.

Both work in the unit cube of the result (coordinates far from 1 would overflow the kd-tree's squared
distances) and give back the input's frame.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass

import numpy as np

from ..shapes.io import sample_surface, with_normals
from ..shapes.shape import Normalization, Shape
from .meshops import face_sides, remove_unreferenced
from .simplify import _dot, _Mesh, _sub

TOLERANCE = 0.2  # the promise: achieved within +-20 % of target_faces (tests/test_facecount.py holds it)
KEEP = 0.1  # a result this close to the target is the model's own, untouched; farther, it is brought to it
BORDER_WEIGHT = 10.0  # of an open border's planes in the quadrics: a border keeps its outline
SPLIT_BAND = 0.75  # a round splits edges at least this share of the longest: long edges go first
MAX_MOVE = 0.3  # a new vertex moves at most this share of its edge's length onto the input (a chord's
# middle lies 0.21 of it off a quarter circle; farther is another part of the input, or a gap the model spanned)
SAMPLES = 32768  # input surface samples new vertices are moved onto (:func:`input_samples`)
NEAREST = 4  # input samples whose tangent planes a new vertex is projected onto (averaged)


@dataclass(frozen=True)
class CountRule:
    """What a face-count target changes in the stages (:func:`count_rule`): the one place that says it.

    Attributes
    ----------
    target : int or None, faces asked for (None: the model chooses)
    low_poly_input : bool, a low-poly mesh input may come back as it is (in place of a generated result)
    snap : bool, vertex cells may move by the cell evidence (``SamplingConfig.snap_margin``)
    remove_flat : bool, the vertices of flat regions may be removed (``TriangleConfig.flat_tol``)
    hold : bool, the result is brought to the count (:func:`hold_count`)
    told : bool, the vertex decoder reads the count (``SamplingConfig.read_count``, ``tell_below``)
    """

    target: int | None
    low_poly_input: bool
    snap: bool
    remove_flat: bool
    hold: bool
    told: bool = False


def count_rule(target: int | None, told: bool = False) -> CountRule:
    """The stages' rule for a ``target_faces`` of ``target``: with a target the result is brought to it.  A
    decoder ``told`` the count (``SamplingConfig.read_count``) made its vertices for it, and they are kept (no
    low-poly input in their place, no move by the cell evidence, no flat vertex removed); otherwise the model's
    own choices stand, as without a target.  A result the networks do not make (the input's planes, its flat
    faces simplified, a low-poly input) is brought to the count all the same."""
    free = target is None or not told
    return CountRule(target=target, low_poly_input=free, snap=free, remove_flat=free, hold=target is not None,
                     told=not free)


def hold_count(vertices: np.ndarray, faces: np.ndarray, target: int, points: np.ndarray | None = None,
               normals: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, str]:
    """The mesh brought to about ``target`` faces, or as it is where it lies within ``KEEP`` of it.

    Parameters
    ----------
    vertices : (V, 3) float
    faces : (F, 3) int, consistently wound where it is a surface
    target : int, faces asked for
    points, normals : (P, 3) float, optional
        Samples of the input surface with their unit normals (either sign), in the frame of ``vertices``:
        the vertices a split makes are moved onto their tangent planes.  Without them they stay at the
        middles of their edges.

    Returns
    -------
    vertices : (V', 3) float64, unused ones dropped after a simplification
    faces : (F', 3) int64
    step : str, "kept" (within ``KEEP`` already), "simplified" or "split"
    """
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    target = int(target)
    if len(f) == 0 or abs(len(f) - target) <= KEEP * target:
        return v, f, "kept"
    norm = Normalization.fit(v)
    if len(f) > target:
        return (*remove_unreferenced(v, decimate(norm.apply(v), f, target))[:2], "simplified")
    surface = None if points is None or normals is None else (norm.apply(np.asarray(points, dtype=np.float64)),
                                                              np.asarray(normals, dtype=np.float64))
    unit, f = split_longest(norm.apply(v), f, target, surface)
    return norm.invert(unit), f, "split"


def input_samples(shape: Shape, n: int = SAMPLES) -> tuple[np.ndarray, np.ndarray]:
    """(M, 3) points of the input surface and (M, 3) unit normals, in its own frame, for :func:`hold_count`: a
    point cloud's own (``n`` of them drawn where it has more), a mesh's ``n`` samples (fixed seed; drawn in the
    unit cube, where the areas of far-apart coordinates cannot overflow)."""
    shape = with_normals(shape)
    if shape.faces is None and len(shape.vertices) <= n:
        return np.asarray(shape.vertices, dtype=np.float64), np.asarray(shape.normals, dtype=np.float64)
    norm = Normalization.fit(shape.vertices)
    points, normals = sample_surface(shape, n, seed=0, vertices=norm.apply(shape.vertices))
    return norm.invert(points), normals.astype(np.float64)


# --------------------------------------------------------------------------- fewer faces


def _plane_quadric(n, d: float, w: float) -> list[float]:
    """The quadric w * (n.x - d)^2 of a plane as its 10 distinct coefficients (xx xy xz xw yy yz yw zz zw ww)."""
    a, b, c, e = n[0], n[1], n[2], -d
    return [w * a * a, w * a * b, w * a * c, w * a * e, w * b * b, w * b * c, w * b * e, w * c * c, w * c * e,
            w * e * e]


def _quadric_error(q: list[float], p) -> float:
    x, y, z = p
    return (q[0] * x * x + 2 * q[1] * x * y + 2 * q[2] * x * z + 2 * q[3] * x + q[4] * y * y + 2 * q[5] * y * z
            + 2 * q[6] * y + q[7] * z * z + 2 * q[8] * z + q[9])


def _trace(q: list[float]) -> float:
    return q[0] + q[4] + q[7]


def _quadrics(mesh: _Mesh) -> list[list[float]]:
    """Per vertex, the area-weighted quadrics of the planes of its faces, plus, along an open border, the
    planes through each border edge upright on its face (weighted ``BORDER_WEIGHT``)."""
    q = [[0.0] * 10 for _ in mesh.p]
    uses: dict[tuple[int, int], list[int]] = {}
    for i, f in enumerate(mesh.faces):
        n = mesh._normal(f)
        area = math.sqrt(_dot(n, n))
        if area > mesh.min_area:
            unit = (n[0] / area, n[1] / area, n[2] / area)
            k = _plane_quadric(unit, _dot(unit, mesh.p[f[0]]), area)
            for x in f:
                q[x] = [s + t for s, t in zip(q[x], k, strict=True)]
        for j in range(3):
            uses.setdefault((min(f[j], f[j - 1]), max(f[j], f[j - 1])), []).append(i)
    for (a, b), around in uses.items():
        if len(around) != 1 or mesh.plane[around[0]] is None:
            continue
        edge = _sub(mesh.p[b], mesh.p[a])
        length2 = _dot(edge, edge)
        n = mesh.plane[around[0]][0]
        up = (edge[1] * n[2] - edge[2] * n[1], edge[2] * n[0] - edge[0] * n[2], edge[0] * n[1] - edge[1] * n[0])
        size = math.sqrt(_dot(up, up))
        if size == 0.0:
            continue
        up = (up[0] / size, up[1] / size, up[2] / size)
        k = _plane_quadric(up, _dot(up, mesh.p[a]), BORDER_WEIGHT * length2)
        for x in (a, b):
            q[x] = [s + t for s, t in zip(q[x], k, strict=True)]
    return q


def decimate(vertices: np.ndarray, faces: np.ndarray, target: int, area_tol: float = 1e-10,
             max_move: float | None = None, keep: np.ndarray | None = None) -> np.ndarray:
    """Half-edge collapses ``v -> u`` of least quadric error until at most ``target`` faces are left (or no
    collapse keeps the surface a surface, or none stays within ``max_move``).

    Parameters
    ----------
    vertices : (N, 3) float, positions (kept: every collapse moves a vertex onto a neighbour)
    faces : (F, 3) int
        Vertices whose faces are not one fan (pinches, edges of three faces) are never removed.
    target : int
    area_tol : float, a triangle of area at most ``area_tol * L**2`` is a sliver (``simplify.collapse_flat``)
    max_move : float or None
        Only collapses that put the merged vertex within this distance of the planes it stands for (the
        root of its quadric's error over the quadric's weight: their area-weighted RMS distance) are made.
    keep : (N,) bool or None, vertices never collapsed away (others may still collapse onto them)

    Returns
    -------
    faces : (G, 3) int64, into the same ``vertices``, windings kept
    """
    pos = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    length = float(np.ptp(pos, axis=0).max()) if len(pos) else 0.0
    mesh = _Mesh(pos, np.asarray(faces, dtype=np.int64).reshape(-1, 3), 2 * area_tol * length**2)
    queue = _Collapses(mesh, max_move, keep)
    alive = sum(mesh.alive)
    # A collapse changes the link condition up to two rings away: passes over every vertex repeat until the
    # target is reached or a pass collapses nothing (the next would be the same pass).
    while alive > target and any([queue.push(v) for v in range(len(mesh.p))]):
        before = alive
        while queue.heap and alive > target:
            _, _, v, u, ver = heapq.heappop(queue.heap)
            if ver != queue.version[v]:
                continue  # re-scored since
            fan = mesh.link(v)
            if fan is None or not mesh.valid(v, u, *fan, math.inf):
                queue.push(v, check=True)
                continue
            alive -= queue.collapse(v, u)
        queue.heap.clear()
        if alive == before:
            break
    return np.array([f for f, a in zip(mesh.faces, mesh.alive, strict=True) if a], dtype=np.int64).reshape(-1, 3)


class _Collapses:
    """The half-edge collapses of :func:`decimate` waiting in a heap, least quadric error first; a vertex's
    entry counts only while its ``version`` is the one it was queued with."""

    def __init__(self, mesh: _Mesh, max_move: float | None = None, keep: np.ndarray | None = None):
        self.mesh, self.bound = mesh, None if max_move is None else max_move * max_move
        self.keep = None if keep is None else np.asarray(keep, dtype=bool)
        self.quadric = _quadrics(mesh)
        self.own = [_quadric_error(q, p) for q, p in zip(self.quadric, mesh.p, strict=True)]  # each at itself
        self.version = [0] * len(mesh.p)
        self.heap: list[tuple[float, float, int, int, int]] = []

    def push(self, v: int, check: bool = False) -> bool:
        """Queue ``v``'s collapse of least error, the shorter edge first among equals (flat regions); with
        ``check``, its least valid one.  Validity is checked when a collapse comes up (most are valid): it
        costs ten times the error."""
        mesh = self.mesh
        self.version[v] += 1
        if self.keep is not None and self.keep[v]:
            return False
        fan = mesh.link(v) if mesh.around[v] else None
        if fan is None:
            return False
        qv, pv = self.quadric[v], mesh.p[v]
        options = sorted((_quadric_error(qv, mesh.p[u]) + self.own[u],
                          _dot(d := _sub(mesh.p[u], pv), d), u) for u in fan[1])
        if self.bound is not None:  # a quadric's weight is its trace: the sum of its planes' weights
            options = [o for o in options if o[0] <= self.bound * (_trace(qv) + _trace(self.quadric[o[2]]))]
        for err, length2, u in options:
            if not check or mesh.valid(v, u, *fan, math.inf):
                heapq.heappush(self.heap, (err, length2, v, u, self.version[v]))
                return True
        return False

    def collapse(self, v: int, u: int) -> int:
        """Collapse ``v`` onto ``u``, ``u`` taking ``v``'s quadric, and queue ``u`` and its neighbours again;
        returns the faces the collapse removed."""
        mesh, quadric = self.mesh, self.quadric
        removed = sum(u in mesh.faces[i] for i in mesh.around[v])
        mesh.collapse(v, u)
        quadric[u] = [s + t for s, t in zip(quadric[u], quadric[v], strict=True)]
        self.own[u] = _quadric_error(quadric[u], mesh.p[u])
        self.version[v] += 1
        for x in mesh.neighbours(u) | {u}:
            self.push(x)
        return removed


# --------------------------------------------------------------------------- more faces


def side_edges(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct undirected edges (E, 2) of ``faces`` (F, 3) and (3F,) the edge of each face side, side
    j of face k (from corner j to corner j + 1) at ``j * F + k``."""
    sides = np.sort(face_sides(faces), axis=1)
    n = int(faces.max()) + 1
    keys, which = np.unique(sides[:, 0] * n + sides[:, 1], return_inverse=True)  # one number: 10x np.unique's rows
    return np.c_[keys // n, keys % n], which.reshape(-1)


def _choose(lengths: np.ndarray, which: np.ndarray, third: np.ndarray, need: int, bisect: bool = True
            ) -> np.ndarray:
    """(S,) edges to split in one round, until they add ``need`` faces: the longest first, none shorter than
    ``SPLIT_BAND`` of the longest that may be split, no two in one face (each face then splits in two), and
    with ``bisect`` each the longest side of every face it bounds (so no angle falls below half the smallest
    one before: longest-edge bisection).

    ``third`` (3F,): the corner facing each face side.  An edge whose faces face one corner (a face twice, or
    a pillow of two) is never split: the faces made would meet along one edge three or four times."""
    n_faces = len(third) // 3
    sides_of = np.bincount(which, minlength=len(lengths))
    corners = np.unique(which * (int(third.max()) + 1) + third) // (int(third.max()) + 1)
    allowed = np.bincount(corners, minlength=len(lengths)) == sides_of
    if bisect:
        longest = lengths[which].reshape(3, n_faces).max(0)  # of each face
        np.logical_and.at(allowed, which, lengths[which] >= (1.0 - 1e-9) * np.tile(longest, 3))
    if not allowed.any():
        return np.zeros(0, dtype=np.int64)
    order = np.argsort(-np.where(allowed, lengths, -1.0), kind="stable")
    side_order = np.argsort(which, kind="stable")
    start = np.concatenate([[0], np.cumsum(sides_of)])
    taken = np.zeros(n_faces, dtype=bool)
    chosen, added, cut = [], 0, SPLIT_BAND * lengths[order[0]]
    for e in order:
        if not allowed[e] or lengths[e] < cut or added >= need:
            break
        around = side_order[start[e]:start[e + 1]] % n_faces
        if taken[around].any():
            continue
        taken[around] = True
        chosen.append(e)
        added += len(around)
    return np.asarray(chosen, dtype=np.int64)


def split_longest(vertices: np.ndarray, faces: np.ndarray, target: int,
                  surface: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Split the longest edges at their middles, in rounds, until there are at least ``target`` faces.

    Parameters
    ----------
    vertices : (N, 3) float
    faces : (F, 3) int
    target : int
    surface : ((P, 3), (P, 3)) float, optional
        Input samples and their normals: each new vertex is moved onto the mean of their tangent planes'
        nearest points (:func:`project`).

    Returns
    -------
    vertices : (N + S, 3) float64, the first N unchanged
    faces : (F', 3) int64, windings kept; a split edge's faces each become two.  Fewer than ``target`` where no
        edge can be split (:func:`_choose`).
    """
    from scipy.spatial import cKDTree

    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    tree = cKDTree(surface[0]) if surface is not None else None
    while len(f) < target:
        edges, which = side_edges(f)
        lengths = np.linalg.norm(v[edges[:, 1]] - v[edges[:, 0]], axis=1)
        third = f[:, [2, 0, 1]].T.reshape(-1)
        chosen = _choose(lengths, which, third, target - len(f))
        if len(chosen) == 0:  # the longest sides of the faces left face one corner twice
            chosen = _choose(lengths, which, third, target - len(f), bisect=False)
        if len(chosen) == 0:
            break  # every edge faces one corner twice: nothing can be split
        middle = np.full(len(edges), -1, dtype=np.int64)
        middle[chosen] = len(v) + np.arange(len(chosen))
        new = 0.5 * (v[edges[chosen, 0]] + v[edges[chosen, 1]])
        if tree is not None:
            new = project(new, tree, surface[0], surface[1], MAX_MOVE * lengths[chosen])[0]
        v = np.concatenate([v, new])
        f = split_sides(f, which, middle)[0]
    return v, f


def split_sides(faces: np.ndarray, which: np.ndarray, middle: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``faces`` (F, 3) with each side whose edge has a ``middle`` vertex (E,; -1: none) split there, each face
    in two (a face has at most one such side; ``which`` (3F,): the edge of each face side, :func:`side_edges`),
    windings kept; and (F',) bool, the faces made (after the faces kept)."""
    side = middle[which]  # (3F,) the new vertex on each face side, -1 where the side stays whole
    k = np.flatnonzero(side >= 0)
    face, j = k % len(faces), k // len(faces)
    a, b, c = faces[face, j], faces[face, (j + 1) % 3], faces[face, (j + 2) % 3]
    keep = np.ones(len(faces), dtype=bool)
    keep[face] = False
    out = np.concatenate([faces[keep], np.c_[a, side[k], c], np.c_[side[k], b, c]])
    return out, np.r_[np.zeros(int(keep.sum()), dtype=bool), np.ones(2 * len(k), dtype=bool)]


def project(points: np.ndarray, tree, samples: np.ndarray, normals: np.ndarray, limit: np.ndarray,
            k: int = NEAREST, facing: np.ndarray | None = None, min_cos: float = 0.0
            ) -> tuple[np.ndarray, np.ndarray]:
    """``points`` (M, 3) moved onto the surface the ``samples`` (P, 3) with unit ``normals`` (P, 3) were
    drawn from: onto the mean of the nearest points of their ``k`` nearest samples' tangent planes
    (on a crease between two flat faces that is the crease itself), at most ``limit`` (M,) away; with ``facing``
    (M, 3) only the samples whose normals (then outward) lie within ``min_cos`` of it count, and a point none
    does stays.  Also (M,) the length of the counted samples' mean normal (1 where the surface is flat there).

    ``tree`` is a ``cKDTree`` of the samples.
    """
    k = min(k, len(samples))
    idx = tree.query(points, k=k)[1].reshape(len(points), k)
    n = normals[idx]  # (M, k, 3)
    agree = np.ones(idx.shape, dtype=bool) if facing is None else np.einsum("mki,mi->mk", n, facing) > min_cos
    off = np.einsum("mki,mki->mk", points[:, None] - samples[idx], n)
    count = np.maximum(agree.sum(1), 1)[:, None]
    move = -((off * agree)[..., None] * n).sum(1) / count
    size = np.linalg.norm(move, axis=1)
    scale = np.where(size > limit, limit / np.maximum(size, 1e-300), 1.0)
    return points + move * scale[:, None], np.linalg.norm((n * agree[..., None]).sum(1), axis=1) / count[:, 0]
