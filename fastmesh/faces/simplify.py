"""Flat-vertex removal: drop the vertices a surface does not need to keep its shape.

An artist puts a vertex where the surface turns: at a corner, along a crease where it bends,
on a curved patch.  A vertex inside a flat region, on a straight crease between two flat
regions or on a straight open border adds triangles and no shape; the decoder emits many of
them, and they are what keeps a box from coming back as eight vertices.

:func:`collapse_flat` removes them by half-edge collapses ``v -> u`` (every face of ``v``
takes ``u`` in its place; the faces on the edge ``v u`` disappear) where ``u`` lies within
``tol`` of the plane of every face around ``v``: the faces that take ``u`` keep their planes.
The test reads the faces as they are, not as they were before earlier collapses, yet errors do
not pile up: as faces grow over a curved region, the planes of neighbouring faces part by more
than ``tol`` and the collapses stop (a sphere of 2,562 vertices keeps 749 and stays within 0.4
cells of the sphere at a ``tol`` of half a cell; tested).  Planes remembered from the first faces around a
vertex measured alike on the held-out meshes and took twice the time (docs/results.md).
A collapse must keep the surface a surface (the link condition, no fold-over, no face
twice), and a vertex on an open border moves only along it, where the border runs straight.
"""

from __future__ import annotations

import heapq
import math

import numpy as np


def _sub(a, b):
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _dot(a, b) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


class _Mesh:
    """A triangle mesh that collapses half-edges in place: faces as index triples and, per
    vertex, the faces around it.  Positions never change, so they are kept as tuples of floats
    (scalar arithmetic on them costs a tenth of numpy's on 3-vectors).  ``min_area``: twice the
    area of a sliver."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, min_area: float):
        self.min_area = min_area
        self.p = [tuple(x) for x in np.asarray(vertices, dtype=np.float64).tolist()]
        self.faces = [list(map(int, f)) for f in faces]
        self.alive = [True] * len(self.faces)
        self.around: list[set[int]] = [set() for _ in range(len(self.p))]
        for i, f in enumerate(self.faces):
            for x in f:
                self.around[x].add(i)
        self.plane = [self._plane(f) for f in self.faces]

    def _normal(self, f):
        p = self.p
        return _cross(_sub(p[f[1]], p[f[0]]), _sub(p[f[2]], p[f[0]]))

    def _plane(self, f):
        """(unit normal, offset) of face ``f``; None for a sliver, whose plane is noise."""
        n = self._normal(f)
        area = math.sqrt(_dot(n, n))
        if area <= self.min_area:
            return None
        n = (n[0] / area, n[1] / area, n[2] / area)
        return n, _dot(n, self.p[f[0]])

    def neighbours(self, v: int) -> set[int]:
        return {x for i in self.around[v] for x in self.faces[i]} - {v}

    def link(self, v: int) -> tuple[str, list[int]] | None:
        """The ring of ``v``: ("interior", cycle) or ("border", path in face order), None where
        the faces around ``v`` are not one fan (a pinch or a non-manifold edge) or there are none."""
        nxt: dict[int, int] = {}
        for i in self.around[v]:
            f = self.faces[i]
            k = f.index(v)
            a, b = f[(k + 1) % 3], f[(k + 2) % 3]
            if a in nxt:
                return None
            nxt[a] = b
        if not nxt:  # no face left around v (a collapse nearby took them all)
            return None
        starts = set(nxt) - set(nxt.values())
        if len(starts) > 1:
            return None
        start = next(iter(starts)) if starts else next(iter(nxt))
        ring, x = [start], nxt.get(start)
        while x is not None and x != start:
            ring.append(x)
            x = nxt.get(x)
            if len(ring) > len(nxt) + 1:
                return None
        kind = "border" if starts else "interior"
        if len(ring) != len(nxt) + (kind == "border"):
            return None  # more than one fan
        return kind, ring

    def error(self, v: int, u: int) -> float:
        """Largest distance of ``u`` from the planes of the faces around ``v`` (slivers' left out)."""
        pu = self.p[u]
        return max((abs(_dot(plane[0], pu) - plane[1]) for plane in map(self.plane.__getitem__, self.around[v])
                    if plane), default=0.0)

    def valid(self, v: int, u: int, kind: str, ring: list[int], tol: float) -> bool:
        """Whether ``v -> u`` keeps a surface, a border vertex on its border within ``tol`` (the
        planes' test is :meth:`error`)."""
        p = self.p
        if kind == "border":
            if u not in (ring[0], ring[-1]):
                return False  # a border vertex moves along its border only
            w = ring[-1] if u == ring[0] else ring[0]
            seg, rel = _sub(p[u], p[w]), _sub(p[v], p[w])
            t = min(1.0, max(0.0, _dot(rel, seg) / max(_dot(seg, seg), 1e-300)))
            off = (rel[0] - t * seg[0], rel[1] - t * seg[1], rel[2] - t * seg[2])
            if _dot(off, off) > tol * tol:
                return False  # the border turns at v
        shared = [i for i in self.around[v] if u in self.faces[i]]
        opposite = {x for i in shared for x in self.faces[i]} - {u, v}
        if self.neighbours(v) & self.neighbours(u) != opposite:
            return False  # link condition: the collapse would pinch the surface
        at_u = {frozenset(self.faces[i]) for i in self.around[u]}
        for i in self.around[v]:
            f = self.faces[i]
            if u in f:
                continue
            moved = [u if x == v else x for x in f]
            if frozenset(moved) in at_u:
                return False  # a face twice (a tetrahedron's tip)
            after = self._normal(moved)
            if _dot(after, self._normal(f)) <= 0 or _dot(after, after) <= self.min_area**2:
                return False  # folds over or flattens to a sliver
        return True

    def collapse(self, v: int, u: int) -> None:
        for i in list(self.around[v]):
            f = self.faces[i]
            if u in f:
                self.alive[i] = False
                for x in f:
                    self.around[x].discard(i)
            else:
                f[f.index(v)] = u
                self.plane[i] = self._plane(f)
                self.around[u].add(i)
        self.around[v] = set()


def collapse_flat(vertices: np.ndarray, faces: np.ndarray, tol: float, area_tol: float = 1e-10) -> np.ndarray:
    """Remove the vertices of flat regions, straight creases and straight borders.

    Parameters
    ----------
    vertices : (N, 3) float
    faces : (F, 3) int
        Consistently wound where the surface is a surface; vertices whose faces are not one fan
        are kept as they are.
    tol : float
        Largest distance (in the vertices' units) a kept vertex may lie from the plane of a
        face it replaces.
    area_tol : float
        A triangle of area at most ``area_tol * L**2`` (L: the vertices' longest bounding-box
        side) is a sliver: its plane is not trusted and no collapse may make one.

    Returns
    -------
    faces : (G, 3) int64
        Into the same ``vertices`` (the removed ones no longer used), windings kept.
    """
    pos = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    length = float(np.ptp(pos, axis=0).max()) if len(pos) else 0.0
    mesh = _Mesh(pos, faces, 2 * area_tol * length**2)
    version = [0] * len(mesh.p)
    heap: list[tuple[float, int, int, int]] = []

    def push(v: int) -> bool:
        """Queue ``v``'s valid collapse of least error (a newer entry makes older ones stale)."""
        version[v] += 1
        fan = mesh.link(v) if mesh.around[v] else None
        if fan is None:
            return False
        for err, u in sorted((mesh.error(v, u), u) for u in fan[1]):
            if err > tol:
                return False
            if mesh.valid(v, u, *fan, tol):
                heapq.heappush(heap, (err, v, u, version[v]))
                return True
        return False

    # A collapse changes the faces around u: its ring is scored again.  It can also change the link
    # condition of vertices two rings away, so passes over every vertex repeat until one finds nothing.
    while any([push(v) for v in range(len(mesh.p))]):
        while heap:
            _, v, u, ver = heapq.heappop(heap)
            if ver != version[v]:
                continue  # re-scored since
            mesh.collapse(v, u)
            version[v] += 1
            for x in mesh.neighbours(u) | {u}:
                push(x)
    return np.array([f for f, a in zip(mesh.faces, mesh.alive, strict=True) if a], dtype=np.int64).reshape(-1, 3)
