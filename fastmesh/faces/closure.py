"""Closure: whether a result should be closed, and closing the holes the face stage left in it.

Step 6's hole filling closes a boundary loop only with faces that lie on the input surface
(``holes.fill_holes``), so an open input stays open.  A closed input's result often keeps small holes
anyway: on thin parts, around spikes, where a triangle over the hole would fold onto its neighbour by a
little more than the selection allows.  When the input is closed (:func:`decide_closed`), the closure
stage closes those loops too (:func:`close_loops`), in steps that give up less each time: the same rules
with the support limit relaxed, then any fold allowed but never an edge in a third face.

Deciding from the input:

- a mesh is closed when, its vertices welded, its edges with one face are at most ``OPEN_SHARE`` of all and
  its openings span at most ``HOLE_AREA_SHARE`` of its area (a dense mesh has few boundary edges however
  wide its openings);
- a point cloud is closed when the generalized winding number of its oriented points (Barill et al.,
  2018) is about 1 just inside the surface and about 0 just outside it, as it is for the samples of a
  closed surface; an open sheet gives about +-1/2 on both sides.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from ..params import CLOSED_CHOICES
from ..shapes.shape import Normalization, Shape
from .holes import WHOLE_LOOP_MAX, _best_triangulation, _close_loop, _simple_loops, _walk_loops, boundary_loops
from .meshops import edge_face_counts, face_sides, triangle_areas, weld
from .orient import orient_faces
from .support import SupportCache, face_samples

# A mesh with at most this share of its (welded) edges on a boundary counts as closed: scans and game
# meshes often have a few cracks that the artist never meant as openings.
OPEN_SHARE = 0.01
# ... and whose openings span at most this share of its surface area (each boundary loop's vector area): a crack
# along a seam spans next to none, where a wide opening counts whatever the mesh's density.  Remeshed to ~20,000
# faces, open artist meshes keep under OPEN_SHARE of their edges on a boundary (a character's lower body open at
# the waist: 0.8 %), their openings spanning 0.8-47 % of their area (docs/results.md).
HOLE_AREA_SHARE = 0.005
# The winding-number test: queries this many point spacings in front of and behind the surface; a pair
# reads "closed" when the winding number is above 1/2 + margin on one side and below 1/2 - margin on the
# other; a point cloud is closed when at least CLOSED_SHARE of the pairs read so.  Measured on closed and
# open shapes of random proportions (tests/test_closure.py) and on the held-out packages' point clouds
# (docs/results.md): the samples of closed primitives read 0.84-0.94, a box without its lid 0.37, a
# hemisphere and a sheet 0; 12 of the 13 watertight references 0.61-0.93.  Nearer queries read the
# gaps between the points.
QUERY_SPACINGS = 2.0
WINDING_MARGIN = 0.4
CLOSED_SHARE = 0.5
_QUERIES = 256
_SOURCES = 16384
# Support limits the closure relaxes to, in steps (times the selection's limit); the last one holds for the
# step that allows folds too.  A cap farther from the input than that covers an opening the input has (a
# nozzle, a sleeve): it stays open.
RELAX = (2.0, 4.0)
# Longest loop the closure closes (by ears, or by a fan about an input point), and the longest it triangulates
# as a whole (that weighs all C(k, 3) triangles of a k-loop: 41,664 at 64 edges, 4,960 at 32).
CLOSE_MAX_LOOP = 64
WHOLE_MAX = 32
# A loop of at most this many edges is a hole of the result, not an opening of the input: its fan about an
# input point (the last step) may stray twice as far as a cap.
SMALL_LOOP = 6


def decide_closed(shape: Shape, closed: str = "auto") -> tuple[bool, str]:
    """Whether to close the result of ``shape``, and why.

    Parameters
    ----------
    shape : Shape
    closed : {"auto", "true", "false"}

    Returns
    -------
    close : bool
    reason : str, one of "asked" (``closed`` was true or false), "closed_mesh", "open_mesh",
        "closed_points", "open_points".
    """
    if closed not in CLOSED_CHOICES:
        raise ValueError(f"closed must be one of {', '.join(CLOSED_CHOICES)}, got {closed!r}")
    if closed != "auto":
        return closed == "true", "asked"
    if shape.faces is not None:
        close = without_openings(shape)
        return close, "closed_mesh" if close else "open_mesh"
    if shape.normals is None:
        return False, "open_points"
    close = winding_closed_share(shape.vertices, shape.normals) >= CLOSED_SHARE
    return close, "closed_points" if close else "open_points"


def without_openings(shape: Shape) -> bool:
    """Whether ``shape`` is a closed mesh: its vertices welded, its edges with one face are at most ``OPEN_SHARE``
    of all and its openings span at most ``HOLE_AREA_SHARE`` of its area.  A point cloud is never known to be
    one."""
    if shape.faces is None:
        return False
    v, f = weld(shape.vertices, shape.faces)
    return _open_share(f) <= OPEN_SHARE and opening_area_share(v, f) <= HOLE_AREA_SHARE


def mesh_open_share(vertices: np.ndarray, faces: np.ndarray) -> float:
    """The share in [0, 1] of the edges of a mesh ((N, 3) ``vertices``, (F, 3) ``faces``) that have one face,
    its vertices welded first (:func:`fastmesh.faces.meshops.weld`: seams are not openings); 1 without faces."""
    return _open_share(weld(vertices, faces)[1])


def _open_share(faces: np.ndarray) -> float:
    if len(faces) == 0:
        return 1.0
    counts = edge_face_counts(faces)
    return float((counts == 1).sum() / len(counts))


def opening_area_share(vertices: np.ndarray, faces: np.ndarray) -> float:
    """The area the openings of a welded mesh span, as a share of its surface area (0 without openings; 1 without
    area): per boundary loop the length of its vector area, half the sum of p_i x p_i+1, which is a flat
    opening's area and next to none for a crack, whose two sides run back along each other.

    Parameters
    ----------
    vertices : (N, 3) float
    faces : (F, 3) int, welded (:func:`fastmesh.faces.meshops.weld`)

    Returns
    -------
    float >= 0
    """
    v = np.asarray(vertices, dtype=np.float64)
    area = float(triangle_areas(v, faces).sum())
    if area <= 0.0:
        return 1.0
    spanned = 0.0
    for loop in boundary_loops(faces):
        p = v[loop] - v[loop].mean(axis=0)
        spanned += 0.5 * float(np.linalg.norm(np.cross(p, np.roll(p, -1, axis=0)).sum(axis=0)))
    return spanned / area


def winding_closed_share(points: np.ndarray, normals: np.ndarray, seed: int = 0) -> float:
    """The share of query pairs at which oriented points enclose a volume.

    Each query pair sits ``QUERY_SPACINGS`` point spacings in front of and behind one point, along its
    normal; a pair reads "closed" when the generalized winding number of all the points is about +-1
    on one side and about 0 on the other (normals may all point inwards: the sign is theirs).

    Parameters
    ----------
    points : (N, 3) float
    normals : (N, 3) float, unit, consistently oriented for a closed answer
    seed : int, of the points chosen as sources and queries

    Returns
    -------
    float in [0, 1]
    """
    rng = np.random.default_rng(seed)
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    if len(p) < 16:
        return 0.0
    p = Normalization.fit(p).apply(p)  # the same winding numbers at any scale, without overflowing squares
    src = rng.choice(len(p), size=min(len(p), _SOURCES), replace=False)
    p, n = p[src], n[src]
    k = 8
    dist = cKDTree(p).query(p, k=k + 1)[0][:, -1]
    area = np.pi * dist**2 / k  # the surface each point stands for
    spacing = float(np.median(dist)) / math.sqrt(k)
    at = rng.choice(len(p), size=min(len(p), _QUERIES), replace=False)
    offset = QUERY_SPACINGS * spacing * n[at]
    inside = _winding(p[at] - offset, p, n, area)
    outside = _winding(p[at] + offset, p, n, area)
    lo, hi = 0.5 - WINDING_MARGIN, 0.5 + WINDING_MARGIN
    good = ((np.abs(inside) > hi) & (np.abs(outside) < lo)) | ((np.abs(outside) > hi) & (np.abs(inside) < lo))
    return float(good.mean())


def _winding(queries: np.ndarray, points: np.ndarray, normals: np.ndarray, area: np.ndarray) -> np.ndarray:
    """(Q,) generalized winding numbers of oriented points (dipoles of strength ``area``) at ``queries``."""
    # As products of (Q, 3) by (3, N): (p - q).n = p.n - q.n and |p - q|^2 = |p|^2 - 2 p.q + |q|^2, without the
    # (Q, N, 3) differences (a sixth of the time).  The cancellation in |p - q|^2 costs ~1e-12 of it at the
    # nearest sources (2 spacings away in the unit cube), far below the margins the decision reads.
    out = np.empty(len(queries))
    pn, pp = np.einsum("ni,ni->n", points, normals), np.einsum("ni,ni->n", points, points)
    for s in range(0, len(queries), 256):  # 256 x N pairs at a time: bounded memory
        q = queries[s:s + 256]
        dot = pn[None] - q @ normals.T
        r2 = np.maximum(pp[None] - 2.0 * (q @ points.T) + np.einsum("qi,qi->q", q, q)[:, None], 1e-24)
        out[s:s + 256] = (area * dot / (r2 * np.sqrt(r2))).sum(1) / (4 * np.pi)
    return out


def close_loops(vertices: np.ndarray, faces: np.ndarray, book, points: np.ndarray, limit: float,
                tree: cKDTree | None = None, max_loop: int = CLOSE_MAX_LOOP, bounded: bool = True
                ) -> tuple[np.ndarray, np.ndarray]:
    """Close the boundary loops of a selected surface, giving up a little more at each step.

    Each loop of at most ``max_loop`` edges is closed, at the first step that closes it, by: ear clipping and (up to
    ``WHOLE_MAX`` edges) whole triangulation under the selection's rules (:func:`fastmesh.faces.holes._close_loop`)
    with the support limit relaxed by each factor of ``RELAX``; then, within the last of them, the whole
    triangulation of least support distance that adds no edge the surface already has, folds allowed (it stays
    edge-manifold); a loop that passes a vertex twice and does not close so is closed in its simple parts. A cap
    with a point farther from the input than the last relaxed limit is not taken: a loop whose every cap strays so
    far is an opening of the input, and stays open (not ``bounded``: the input has no openings, and every loop is
    closed however far its cap strays). A loop that nothing on its own vertices closes gets a fan about a new
    vertex, the input point nearest its middle.

    Parameters
    ----------
    vertices : (N, 3) float
    faces : (F, 3) int, the selection, its bookkeeping in ``book`` (``selection.Selection``)
    book : the selection's bookkeeping; closing faces are added to it
    points : (P, 3) float, samples of the input surface
    limit : float, the selection's support limit
    tree : cKDTree of ``points``, optional
    max_loop : int
    bounded : bool, caps held to the last relaxed limit

    Returns
    -------
    vertices : (N + k, 3) float64, ``vertices`` and the k the closure added (:func:`_fan`)
    faces : (F', 3) int64, ``faces`` and the closing faces (windings to be made consistent by the caller)
    """
    # A cap may lie on the input by the median of each face and still cross an opening: its farthest point counts.
    reach = limit * RELAX[-1] if bounded else np.inf
    support = SupportCache(vertices, points, tree, bound=reach)  # no step compares with more than reach
    tree = support.tree

    def near(faces):
        if faces and _farthest(vertices, faces, tree) > reach:
            for t in faces:
                book.remove(*t)
            return None
        return faces

    out = [tuple(t) for t in orientable(vertices, faces, book).tolist()]
    for relax in RELAX:
        for loop in hole_loops(vertices, np.asarray(out, dtype=np.int64)):
            if len(loop) <= max_loop:
                out += _relaxed_cap(loop, book, support, limit * relax, near) or []
    for loop in hole_loops(vertices, np.asarray(out, dtype=np.int64)):
        out += _folded_cap(loop, book, support, reach, near) or []
    # Last, a loop no triangulation of its own vertices closes gets a vertex of the input's: the input point
    # nearest its middle, joined to each of its edges (new edges only: it stays edge-manifold).
    added: list[np.ndarray] = []
    for loop in hole_loops(vertices, np.asarray(out, dtype=np.int64)):
        for part in _simple_loops(loop) if len(set(loop)) < len(loop) else [loop]:
            if 3 <= len(part) <= max_loop:
                out += _fan(part, vertices, added, book, support.points, tree,
                            2 * reach if len(part) <= SMALL_LOOP else reach)
    v = np.concatenate([np.asarray(vertices, dtype=np.float64).reshape(-1, 3), *[a[None] for a in added]])
    return v, np.asarray(out, dtype=np.int64).reshape(-1, 3)


def _relaxed_cap(loop: list[int], book, support: SupportCache, limit: float, near) -> list | None:
    """The faces closing ``loop`` under the selection's rules within the support ``limit``: by ear clipping,
    else (a pinched loop, or one over ``WHOLE_LOOP_MAX`` edges, up to ``WHOLE_MAX``) by its whole
    triangulation; ``near`` takes back a cap that strays too far.  None where neither closes it."""
    pinched = len(set(loop)) < len(loop)  # ears would clip across the vertex it passes twice
    ears = None if pinched else near(_close_loop(loop, book, support, limit))
    if ears is None and (pinched or len(loop) > WHOLE_LOOP_MAX) and len(loop) <= WHOLE_MAX:
        ears = near(_best_triangulation(loop, book, support, limit))
    return ears


def _folded_cap(loop: list[int], book, support: SupportCache, reach: float, near) -> list | None:
    """The whole triangulation of ``loop`` within ``reach`` that adds no edge the surface has, folds allowed;
    a pinched loop that does not close so closed in its simple parts.  None where nothing closes it."""
    faces = None
    if len(loop) <= WHOLE_MAX:
        faces = near(_best_triangulation(loop, book, support, reach, folds=True))
    if faces is None and len(set(loop)) < len(loop):  # a pinched loop that cannot close whole: in parts
        faces = [t for part in _simple_loops(loop) if 3 <= len(part) <= WHOLE_MAX
                 for t in near(_best_triangulation(part, book, support, reach, folds=True)) or []]
    return faces


def _fan(loop: list[int], vertices: np.ndarray, added: list, book, points: np.ndarray, tree: cKDTree,
         reach: float) -> list[tuple[int, int, int]]:
    """Faces joining each edge of ``loop`` to a new vertex at the input point nearest the loop's middle
    (appended to ``added``, its index after ``vertices`` and the earlier ones), or none when a face would
    stray farther than ``reach`` from the input or an edge of the loop is no longer open."""
    rim = list(zip(loop, loop[1:] + loop[:1], strict=True))
    if any(len(book.third.get((a, b) if a < b else (b, a), ())) != 1 for a, b in rim):
        return []
    v = np.asarray(vertices, dtype=np.float64)
    known = np.concatenate([v, *[a[None] for a in added]]) if added else v
    centre = points[tree.query(known[loop].mean(0))[1]]
    x = len(known)
    faces = [(a, b, x) for a, b in rim]
    if _farthest(np.concatenate([known, centre[None]]), faces, tree) > reach:
        return []
    added.append(centre)
    book.add_vertex(centre)
    for t in faces:
        book.add(*t)
    return faces


def _farthest(vertices: np.ndarray, faces: list, tree: cKDTree) -> float:
    """The largest distance from a point of ``faces`` (vertex triples; a grid inside each) to the input."""
    return float(tree.query(face_samples(vertices, np.asarray(faces, dtype=np.int64)).reshape(-1, 3))[0].max())


def orientable(vertices: np.ndarray, faces: np.ndarray, book, rounds: int = 8) -> np.ndarray:
    """``faces`` wound consistently, less the faces that keep them from it (also taken out of ``book``).

    A selection can hold a twisted strip (a thin part whose faces join its two sides): no winding then
    agrees across every edge, and a result with faces turned inside out is no asset.  Where two faces run
    the same way along their edge after :func:`orient_faces`, the later one goes; the hole it leaves is
    closed again, wound like its rim.  A few rounds, as each winding is found anew.
    """
    f = orient_faces(vertices, faces)
    for _ in range(rounds):
        half = face_sides(f)
        again = np.ones(len(half), dtype=bool)
        again[np.unique(half, axis=0, return_index=True)[1]] = False  # a half-edge met a second time
        clash = np.unique(np.flatnonzero(again) % len(f))
        if len(clash) == 0:
            break
        for t in f[clash].tolist():
            book.remove(*t)
        f = orient_faces(vertices, np.delete(f, clash, axis=0))
    return f


def hole_loops(vertices: np.ndarray, faces: np.ndarray) -> list[list[int]]:
    """The holes of an oriented surface as loops of vertices, crossing from fan to fan where they pass a
    vertex twice.

    Where two fans of faces meet at one vertex with the hole on either side (the surface pinched there),
    the hole's loop passes the vertex twice.  Split there into two loops, each closes one fan into a cone,
    and the two cones keep touching at the vertex.  Kept whole, and walked so that it leaves each vertex
    along the boundary edge next clockwise (about the vertex's normal) from the edge it arrived by, the
    loop turns across the gap between the fans at each visit: its triangulation puts faces in both gaps
    and joins the fans into one disc (``holes._best_triangulation`` makes no face of the two visits).

    Parameters
    ----------
    vertices : (N, 3) float
    faces : (F, 3) int, consistently wound

    Returns
    -------
    list of vertex lists (unclosed, at least three vertices each, a vertex listed once per visit); edges of
    more than one face are left out.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(f) == 0:
        return []
    half = face_sides(f)
    _, inverse, counts = np.unique(np.sort(half, axis=1), axis=0, return_inverse=True, return_counts=True)
    hole = half[counts[inverse.reshape(-1)] == 1][:, ::-1]  # a hole runs against its faces' winding
    normal = np.zeros_like(v)
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    for k in range(3):
        np.add.at(normal, f[:, k], n)
    leave: dict[int, list[int]] = {}
    for a, b in hole.tolist():
        leave.setdefault(a, []).append(b)
    loops, stray = [], []
    for a0, b0 in hole.tolist():
        if b0 not in leave.get(a0, ()):
            continue  # walked already
        leave[a0].remove(b0)
        loop, prev, cur = [a0], a0, b0
        while cur != a0 and leave.get(cur):
            loop.append(cur)
            nxt = _next_clockwise(v, normal[cur], prev, cur, leave[cur])
            leave[cur].remove(nxt)
            prev, cur = cur, nxt
        if cur == a0:
            loops.append(loop)
        else:  # faces wound against each other around the hole: no directed way round
            stray += [sorted(e) for e in zip(loop, loop[1:] + [cur], strict=True)]
    # What the directed walk could not go round is walked as undirected edges (split where it meets itself).
    return [x for x in loops if len(x) >= 3] + _walk_loops(sorted(stray))


def _next_clockwise(v: np.ndarray, normal: np.ndarray, prev: int, at: int, choices: list[int]) -> int:
    """Of ``choices`` (vertices across boundary edges from ``at``), the one first met turning clockwise
    about ``normal`` from the direction of ``prev`` (the faces of ``prev``'s edge lie counter-clockwise)."""
    if len(choices) == 1:
        return choices[0]
    d0 = v[prev] - v[at]
    best, angle = choices[0], math.inf
    for w in choices:
        d = v[w] - v[at]
        turn = -math.atan2(float(np.dot(np.cross(d0, d), normal)), float(np.dot(d0, d))) % (2 * math.pi)
        if turn < angle:
            best, angle = w, turn
    return best
