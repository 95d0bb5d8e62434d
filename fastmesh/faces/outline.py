"""Flat regions triangulated from their outlines: few faces where a generated surface is flat.

The decoder places vertices inside flat faces and along straight creases, each a little off its plane (its cell,
the enhancer's error), so a collapse that must keep every face around a vertex in its plane
(``simplify.collapse_flat``) stops at the first face tilted by that noise, and a box comes back with several times
the artist's faces.  Here the faces are grouped first into flat regions (:func:`regions_within`: joined edge to
edge, each face within ``degrees`` of its region's plane and its corners within ``tol`` of it), and each region is
cut again from its outline alone (:func:`outlined`): the vertices inside it go, so do the vertices of its outline
where the outline runs straight (within ``tol``) between two flat regions or along an open border, and the outline
is triangulated in the region's plane (``manifold3d.triangulate``, which keeps the outline's edge directions: the
new faces wind as the region's did, and the surface stays as closed as it was).  A vertex any other face uses
stays, so the curved parts around a flat region keep every vertex and meet it without a gap.  Where a side cut
straight would cross another (a corner of the outline nearer it than the tolerance) it keeps its vertices; a
region whose outline still is no simple polygon in its plane keeps its faces, and so do the vertices it shares.
``kitbash.flat_rebuild`` does the same for a boolean union's exactly coplanar faces; this one tolerates the noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import manifold3d
import numpy as np

from ..shapes.arrangement import plane_basis, signed_area
from ..tokenizer.grid import CELL
from .crossings import crossing_faces
from .meshops import face_normals, face_sides, remove_unreferenced

# A face lower than this many tolerances (twice its area over its longest side) is a sliver, whose normal may tilt
# further from its region's; no face joins a region with its normal MAX_TILT degrees or more from the region's
# (``regions_within``).
SLIVER = 2.0
MAX_TILT = 80.0


@dataclass(frozen=True)
class OutlineConfig:
    """Tolerances of :func:`outlined`, relative to the mesh's longest side.

    Attributes
    ----------
    degrees : a face joins a region within this angle of the region's plane
    tol : ... with its corners within this distance of it; an outline vertex goes within it of the straight line

    On the 60 held-out point clouds' results of the code before (0bca80f, saved by ``fastmesh eval --save``;
    ``benchmarks/outline_sweep.py``, raw ``outline_sweep.txt``) faces per reference face fell from 1.39 to 1.23 on
    average at these, 1.23 at 15 degrees, 1.26 at half a cell; the outlined meshes' fits
    (``support.weighed_fit``) were 1.008 times the results' on average, at most 1.13.
    """

    degrees: float = 10.0
    tol: float = CELL


def regions_within(vertices: np.ndarray, faces: np.ndarray, degrees: float, tol: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Faces grouped into flat regions, largest faces first, across edges of two faces wound alike.

    Parameters
    ----------
    vertices : (N, 3) float
    faces : (F, 3) int
    degrees : float, a face's normal within this angle of its region's (a sliver's further: ``SLIVER``)
    tol : float, every corner of a face within this distance of its region's plane (in the vertices' units)

    Returns
    -------
    labels : (F,) int, the region of each face
    normals : (R, 3) float, the unit normal of each region (its faces' area-weighted)
    """
    v, f = np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    n2 = face_normals(v, f)
    area = np.linalg.norm(n2, axis=1)
    unit = n2 / np.maximum(area, 1e-300)[:, None]
    centre = v[f].mean(1)
    near = _neighbours(f)
    # A sliver's normal says little: corners within ``tol`` of its region's plane tilt it by up to
    # atan(2 tol / its height), 45 degrees or more, and it may tilt that much more.  Never up to MAX_TILT: a sliver
    # of a side that crosses the region's (along a crease) stays out of it.
    height = area / np.maximum(np.linalg.norm(v[f] - v[f[:, [1, 2, 0]]], axis=2).max(1), 1e-300)
    tilt = np.where(height < SLIVER * tol, degrees + np.degrees(np.arctan2(2 * tol, height)), degrees)
    loose = np.cos(np.radians(np.minimum(tilt, MAX_TILT)))
    labels, normals = np.full(len(f), -1), []
    for seed in np.argsort(-area, kind="stable"):
        if labels[seed] >= 0:
            continue
        r = len(normals)
        labels[seed] = r
        sum_n, sum_c, sum_a = n2[seed].copy(), area[seed] * centre[seed], area[seed]
        normal, point, queue = unit[seed], centre[seed], [seed]
        while queue:
            for g in near[queue.pop()]:
                if labels[g] >= 0 or unit[g] @ normal <= loose[g] or np.abs((v[f[g]] - point) @ normal).max() > tol:
                    continue
                labels[g] = r
                queue.append(g)
                sum_n, sum_c, sum_a = sum_n + n2[g], sum_c + area[g] * centre[g], sum_a + area[g]
                normal, point = sum_n / max(np.linalg.norm(sum_n), 1e-300), sum_c / max(sum_a, 1e-300)
        normals.append(normal)
    return labels, np.array(normals).reshape(-1, 3)


def _neighbours(f: np.ndarray) -> list[list[int]]:
    """Per face, the faces across its edges that have two faces wound alike (one side each way)."""
    sides, owner, count = _sides(f)
    index = {(int(a), int(b)): int(k) for k, (a, b) in zip(owner, sides, strict=True)}
    near: list[list[int]] = [[] for _ in range(len(f))]
    for k, (a, b), c in zip(owner, sides, count, strict=True):
        g = index.get((int(b), int(a)))
        if c == 2 and g is not None and g != k:
            near[int(k)].append(g)
    return near


def _sides(f: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(3F, 2) the sides of the faces (``meshops.face_sides``), (3F,) the face of each and how many faces its
    edge has."""
    sides = face_sides(f)
    _, inverse, count = np.unique(np.sort(sides, axis=1), axis=0, return_inverse=True, return_counts=True)
    return sides, np.tile(np.arange(len(f)), 3), count[inverse.reshape(-1)]


def outlined(vertices: np.ndarray, faces: np.ndarray, cfg: OutlineConfig = OutlineConfig()
             ) -> tuple[np.ndarray, np.ndarray, int]:
    """The mesh with each flat region triangulated from its outline (see the module's docstring).

    Parameters
    ----------
    vertices : (N, 3) float
    faces : (F, 3) int
    cfg : OutlineConfig

    Returns
    -------
    vertices : (M, 3) float, those still used
    faces : (G, 3) int64
    removed : int, the vertices that went
    """
    v, f = np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(f) < 2:
        return v, f, 0
    tol = cfg.tol * float(np.ptp(v, axis=0).max())
    labels, normals = regions_within(v, f, cfg.degrees, tol)
    regions = _Regions(v, f, labels, normals)
    gone = regions.removable(tol)
    tried: set[int] = set()
    while True:
        made, failed, restored = regions.triangulated(gone)
        if not failed and not restored:
            out, failed = _assembled(v, f, labels, made, regions.count)
            if not failed:
                break
        for r in failed:  # its whole outline first, then its faces as they are
            gone[f[labels == r] if r in tried else np.concatenate(regions.loops[r])] = False
            tried.add(r)
    v2, f2, _ = remove_unreferenced(v, out)
    return v2, f2, int(len(np.unique(f)) - len(np.unique(out)))


def _assembled(v: np.ndarray, f: np.ndarray, labels: np.ndarray, made: dict[int, np.ndarray],
               was: dict[tuple[int, int], int]) -> tuple[np.ndarray, list[int]]:
    """The faces ``f`` (F, 3) with those of each region in ``made`` ({region: (T, 3) faces}) in place of its own,
    and the regions whose new faces cross another face (``crossings.crossing_faces``) or give an edge more faces
    than it had in ``f`` (``was``: {(i, j), i < j: faces}) and more than two (a diagonal that another face already
    has as a side): a region cut again must leave the surface as free of folds and as manifold as it was."""
    old = f[~np.isin(labels, list(made))]
    new = np.concatenate([old[:0], *made.values()]).astype(np.int64).reshape(-1, 3)
    owner = np.concatenate([np.zeros(0, dtype=np.int64)] + [np.full(len(t), r) for r, t in made.items()])
    out = np.concatenate([old, new])
    fresh = np.r_[np.zeros(len(old), dtype=bool), np.ones(len(new), dtype=bool)]
    bad = crossing_faces(v, out, among=fresh)
    sides, owner_of_side, count = _sides(out)
    crowded = np.array([c > max(2, was.get(e, 0)) for e, c in
                        zip(map(tuple, np.sort(sides, axis=1).tolist()), count.tolist(), strict=True)], dtype=bool)
    bad[owner_of_side[crowded]] = True
    return out, sorted({int(r) for r in owner[bad[len(old):]]})


class _Regions:
    """The flat regions of a mesh with their outlines: per region of two faces or more whose outline is simple
    (each outline vertex passed once; as many loops as a disc with holes has), its loops of vertex ids, wound as
    its faces are."""

    def __init__(self, v: np.ndarray, f: np.ndarray, labels: np.ndarray, normals: np.ndarray):
        self.v, self.f, self.labels, self.normals = v, f, labels, normals
        sides, owner, count = _sides(f)
        self.count = {(int(min(a, b)), int(max(a, b))): int(c) for (a, b), c in zip(sides, count, strict=True)}
        mine = {(int(a), int(b)): int(labels[k]) for (a, b), k in zip(sides, owner, strict=True)}
        border = np.array([c != 2 or mine.get((int(b), int(a))) != labels[k]
                           for (a, b), k, c in zip(sides, owner, count, strict=True)], dtype=bool)
        self.on_outline = np.zeros(len(v), dtype=bool)
        self.on_outline[sides[border, 0]] = True
        self.on_fin = np.zeros(len(v), dtype=bool)
        self.on_fin[sides[count > 2].ravel()] = True
        corners = np.unique(np.c_[f.ravel(), np.repeat(labels, 3)], axis=0)
        self.vertex_labels: dict[int, list[int]] = {}
        for vertex, label in corners:
            self.vertex_labels.setdefault(int(vertex), []).append(int(label))
        self.loops: dict[int, list[np.ndarray]] = {}
        self.around: dict[int, dict[int, tuple[int, int]]] = {}  # per region, each outline vertex's (prev, next)
        for r in np.flatnonzero(np.bincount(labels) >= 2):
            loops = _loops(sides[border & (labels[owner] == r)])
            if loops is not None and _a_disc_with_holes(f[labels == r], loops):
                self.loops[int(r)] = loops
                self.around[int(r)] = {int(x): (int(p), int(n)) for loop in loops
                                       for p, x, n in zip(np.roll(loop, 1), loop, np.roll(loop, -1), strict=True)}

    def removable(self, tol: float) -> np.ndarray:
        """(N,) bool: the vertices inside a region, and those of its outlines that lie within ``tol`` of the
        straight line the outline runs along without them (:func:`_straight`)."""
        gone = np.zeros(len(self.v), dtype=bool)
        for x, labs in self.vertex_labels.items():
            gone[x] = len(labs) == 1 and labs[0] in self.loops and not self.on_outline[x] and not self.on_fin[x]
        decided: set[int] = set()
        for r, loops in self.loops.items():
            for loop in loops:
                free = np.array([self._passes(int(x), r) for x in loop], dtype=bool)
                for run in _runs(loop, free, self.v):
                    if run[1] in decided:
                        continue
                    decided.update(run[1:-1].tolist())
                    gone[run[1:-1]] = ~_straight(self.v[run], tol)[1:-1]
        return gone

    def _passes(self, x: int, r: int) -> bool:
        """Whether outline vertex ``x`` of region ``r`` only passes between two edges of one crease with one other
        region (or of one open border), so both regions lose it alike."""
        labs = self.vertex_labels[x]
        if self.on_fin[x] or any(label not in self.loops for label in labs) or len(labs) > 2:
            return False
        p, n = self.around[r][x]
        if len(labs) == 1:
            return self.count[min(p, x), max(p, x)] == 1 and self.count[min(x, n), max(x, n)] == 1
        other = labs[0] if labs[1] == r else labs[1]
        return self.around[other].get(x) == (n, p) and self.count[min(p, x), max(p, x)] == 2 and \
            self.count[min(x, n), max(x, n)] == 2

    def triangulated(self, gone: np.ndarray) -> tuple[dict[int, np.ndarray], list[int], bool]:
        """Each region that loses a vertex triangulated from its outline without the ``gone`` vertices (N,):
        {region: (T, 3) faces}; the regions whose outline is then no simple polygon in their plane; and whether
        a side cut straight crossed another (a corner nearer it than the tolerance), its vertices then taken out of
        ``gone`` (in place) and its region left for the next round."""
        made, failed, restored = {}, [], False
        for r, loops in self.loops.items():
            if not gone[self.f[self.labels == r]].any():
                continue
            back, crossing = _crossed(self.v, loops, gone, self.normals[r])
            if len(back):
                gone[back], restored = False, True
                continue
            kept = [loop[~gone[loop]] for loop in loops]
            faces = None if crossing or min(map(len, kept)) < 3 else _triangulate(self.v, kept, self.normals[r])
            if faces is None:
                failed.append(r)
            else:
                made[r] = faces
        return made, failed, restored


def _crossed(v: np.ndarray, loops: list[np.ndarray], gone: np.ndarray, normal: np.ndarray
             ) -> tuple[np.ndarray, bool]:
    """The ``gone`` vertices of the outline ``loops`` that a side crossing another side skips, once the loops
    without the ``gone`` vertices (N,) are seen along ``normal``; and whether any side crosses another."""
    at = [np.flatnonzero(~gone[loop]) for loop in loops]
    if min(map(len, at)) < 3:
        return np.zeros(0, dtype=np.int64), False
    sides = _crossing_sides([v[loop[k]] @ plane_basis(normal) for loop, k in zip(loops, at, strict=True)])
    starts = np.cumsum([0] + [len(k) for k in at])
    back = []
    for s in sides:
        j = int(np.searchsorted(starts, s, side="right")) - 1
        loop, k, i = loops[j], at[j], s - starts[j]
        a, b = k[i], k[(i + 1) % len(k)]
        back.append(loop[a + 1:b] if b > a else np.r_[loop[a + 1:], loop[:b]])
    return (np.concatenate(back) if back else np.zeros(0, dtype=np.int64)), len(sides) > 0


def _loops(sides: np.ndarray) -> list[np.ndarray] | None:
    """The closed loops of directed ``sides`` (S, 2), or None where a vertex starts two of them (a pinch)."""
    after = {}
    for a, b in sides:
        if int(a) in after:
            return None
        after[int(a)] = int(b)
    loops = []
    while after:
        start = next(iter(after))
        loop, x = [start], after.pop(start)
        while x != start:
            if x not in after:
                return None
            loop.append(x)
            x = after.pop(x)
        loops.append(np.array(loop, dtype=np.int64))
    return loops


def _a_disc_with_holes(faces: np.ndarray, loops: list[np.ndarray]) -> bool:
    """Whether faces (F, 3) with these outline loops make a disc with ``len(loops) - 1`` holes (Euler: V - E + F
    = 2 - loops)."""
    edges = len(np.unique(np.sort(face_sides(faces), axis=1), axis=0))
    return len(np.unique(faces)) - edges + len(faces) == 2 - len(loops)


def _runs(loop: np.ndarray, free: np.ndarray, v: np.ndarray) -> list[np.ndarray]:
    """The runs of ``free`` vertices (L,) of a ``loop`` (L,) between two fixed ones, each with its two ends; a
    loop with no fixed vertex is fixed at its lowest id and the vertex farthest from it (alike from each side)."""
    if not free.any():
        return []
    if free.all():
        first = int(np.argmin(loop))
        far = int(np.argmax(np.linalg.norm(v[loop] - v[loop[first]], axis=1)))
        free = free.copy()
        free[[first, far]] = False
    start = int(np.flatnonzero(~free)[0])
    loop, free = np.roll(loop, -start), np.roll(free, -start)
    fixed = np.r_[np.flatnonzero(~free), len(loop)]
    looped = np.r_[loop, loop[:1]]
    return [looped[a:b + 1] for a, b in zip(fixed[:-1], fixed[1:], strict=True) if b - a > 1]


def _straight(points: np.ndarray, tol: float) -> np.ndarray:
    """(K,) bool, the points of a polyline (K, 3) Douglas-Peucker keeps at ``tol``: its ends, and the farthest from
    the line between two kept ones while it lies farther than ``tol``."""
    keep = np.zeros(len(points), dtype=bool)
    keep[[0, -1]] = True
    stack = [(0, len(points) - 1)]
    while stack:
        a, b = stack.pop()
        if b - a < 2:
            continue
        d = _off_segment(points[a + 1:b], points[a], points[b])
        k = int(np.argmax(d))
        if d[k] > tol:
            keep[a + 1 + k] = True
            stack += [(a, a + 1 + k), (a + 1 + k, b)]
    return keep


def _off_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(K,) distances of points (K, 3) from the segment a-b."""
    ab = b - a
    t = np.clip((p - a) @ ab / max(float(ab @ ab), 1e-300), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * ab), axis=1)


def _triangulate(v: np.ndarray, loops: list[np.ndarray], normal: np.ndarray) -> np.ndarray | None:
    """(T, 3) the triangles of a polygon with holes given as loops of vertex ids (outer one way round ``normal``,
    holes the other) whose sides cross none of each other (:func:`_crossed`), in the plane of ``normal``; None where
    the loops, seen along it, are no polygon with holes (not one outer loop) or the triangles not its own."""
    flat = [v[loop] @ plane_basis(normal) for loop in loops]
    areas = np.array([signed_area(p) for p in flat])
    if (areas > 0).sum() != 1:
        return None
    tri = np.asarray(manifold3d.triangulate(flat), dtype=np.int64).reshape(-1, 3)
    ids, pts = np.concatenate(loops), np.concatenate(flat)
    t = pts[tri]
    e1, e2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    signed = 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    expected = len(ids) + 2 * (len(loops) - 1) - 2
    if len(tri) != expected or (signed <= 0).any() or not np.isclose(signed.sum(), areas.sum(), rtol=1e-6):
        return None
    return ids[tri]


def _crossing_sides(flat: list[np.ndarray], chunk: int = 256) -> np.ndarray:
    """The sides of these 2D loops (side i of loop k numbered after every side of the loops before it) that cross
    or touch another side, not a neighbour of theirs in one loop; ``chunk`` sides against all at a time."""
    a = np.concatenate(flat)
    b = np.concatenate([np.roll(p, -1, axis=0) for p in flat])
    starts = np.cumsum([0] + [len(p) for p in flat])[:-1]
    nxt = np.concatenate([np.roll(np.arange(len(p)) + o, -1) for p, o in zip(flat, starts, strict=True)])
    hits = []
    for first in range(0, len(a), chunk):
        i, j = np.meshgrid(np.arange(first, min(first + chunk, len(a))), np.arange(len(a)), indexing="ij")
        i, j = i.ravel(), j.ravel()
        keep = (i < j) & (i != nxt[j]) & (nxt[i] != j)
        i, j = i[keep], j[keep]
        d1, d2 = _turn(a[i], b[i], a[j]), _turn(a[i], b[i], b[j])
        d3, d4 = _turn(a[j], b[j], a[i]), _turn(a[j], b[j], b[i])
        hit = (d1 * d2 <= 0) & (d3 * d4 <= 0)
        hits += [i[hit], j[hit]]
    return np.unique(np.concatenate(hits)) if hits else np.zeros(0, dtype=np.int64)


def _turn(p: np.ndarray, q: np.ndarray, r: np.ndarray) -> np.ndarray:
    """(K,) the sign of the turn p -> q -> r of 2D points (K, 2) each."""
    return np.sign((q[:, 0] - p[:, 0]) * (r[:, 1] - p[:, 1]) - (q[:, 1] - p[:, 1]) * (r[:, 0] - p[:, 0]))
