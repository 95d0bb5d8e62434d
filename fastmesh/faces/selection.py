"""The surface selection's bookkeeping (:class:`Selection`): which faces are on each edge, the sector each face
covers around each corner in the tangent plane there, the boundary, and which way each face must be wound to agree
with its piece (:class:`Windings`), so that a face is tested against the selection in near-constant time
(:meth:`Selection.fits`) by the selection and by hole filling alike."""

from __future__ import annotations

import math

import numpy as np

# Share of the narrower corner two faces around a vertex may overlap in the tangent plane there
# (projection onto an estimated plane is inexact on curved and sharp parts).
_SECTOR_SLACK = 0.25
# A face farther than acos(this) from a vertex's tangent plane is not compared in that plane.
_CREASE = 0.5
# Faces at a vertex without a usable tangent plane overlap only when closer than acos(this) in angle.
_PARALLEL = 0.9


def _folded(v: list, a: int, b: int, c: int, d: int, min_cos: float) -> bool:
    """Whether faces (a, b, c) and (a, b, d) fold onto each other across edge (a, b): the angle between
    them around the edge is below the one whose cosine is ``min_cos``."""
    ax, ay, az = v[a]
    ex, ey, ez = v[b][0] - ax, v[b][1] - ay, v[b][2] - az
    ee = ex * ex + ey * ey + ez * ez or 1e-300
    out = []
    for w in (c, d):
        px, py, pz = v[w][0] - ax, v[w][1] - ay, v[w][2] - az
        k = (px * ex + py * ey + pz * ez) / ee
        out.append((px - k * ex, py - k * ey, pz - k * ez))
    (ux, uy, uz), (wx, wy, wz) = out
    nu = math.sqrt(ux * ux + uy * uy + uz * uz) * math.sqrt(wx * wx + wy * wy + wz * wz)
    return nu == 0 or (ux * wx + uy * wy + uz * wz) / nu > min_cos


def _cross(a, b) -> list[float]:
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def _unit(a) -> list[float]:
    n = math.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2]) or 1e-300
    return [a[0] / n, a[1] / n, a[2] / n]


def _normal(v: list, a: int, b: int, c: int) -> list[float]:
    """Unit normal of triangle (a, b, c) of the vertex list ``v``."""
    return _unit(_cross([v[b][i] - v[a][i] for i in range(3)], [v[c][i] - v[a][i] for i in range(3)]))


def _arc(v: list, a: int, b: int, c: int, frame) -> tuple[float, float]:
    """(start, width) in radians of the corner at ``a`` of triangle (a, b, c), projected onto the plane
    of ``frame`` (two orthonormal directions)."""
    (ux, uy, uz), (wx, wy, wz) = frame
    ax, ay, az = v[a]
    ang = []
    for x in (b, c):
        px, py, pz = v[x][0] - ax, v[x][1] - ay, v[x][2] - az
        ang.append(math.atan2(px * wx + py * wy + pz * wz, px * ux + py * uy + pz * uz))
    lo, hi = min(ang), max(ang)
    return (lo, hi - lo) if hi - lo <= math.pi else (hi, 2 * math.pi - (hi - lo))


def _arcs_overlap(s0: float, w0: float, s1: float, w1: float) -> bool:
    """Whether arcs [s0, s0 + w0] and [s1, s1 + w1] of the circle share more than ``_SECTOR_SLACK`` of
    the narrower one."""
    d = (s1 - s0) % (2 * math.pi)
    inter = max(min(w0, d + w1) - d, 0.0) + max(min(w1, 2 * math.pi - d + w0) - (2 * math.pi - d), 0.0)
    return inter > _SECTOR_SLACK * min(w0, w1)


def _runs_down(face: tuple[int, int, int], x: int, y: int) -> int:
    """1 where ``face`` (a, b, c), as wound, runs its edge from the larger of ``x``, ``y`` to the smaller, else 0."""
    lo, hi = (x, y) if x < y else (y, x)
    a, b, c = face
    return int((a, b) == (hi, lo) or (b, c) == (hi, lo) or (c, a) == (hi, lo))


Key = tuple[int, int, int]  # a face named by its sorted corners


class Windings:
    """Which way each selected face must turn for its edge-connected piece to be wound one way, and which way the
    input's normals ask each piece to face: a union-find over the faces whose parity says whether a face is turned
    against its parent, and for each root the turning that makes the piece face along the input (None where none of
    its faces says).  Two faces across an edge agree when they run it opposite ways.  A face whose neighbours ask
    both windings of it would close a strip twisted like a Moebius band, which no turning mends; one that would join
    pieces the input asks to face opposite ways (a sheet folded back over itself, a leg's outside joined to another's
    inside) would make a piece no turning shows from the front: a renderer shows the back of part of either.
    :meth:`Selection.fits` refuses both.  A union-find cannot split, so removing a face leaves the classes to be
    built again (:meth:`Selection.windings`)."""

    def __init__(self):
        self.wound: dict[Key, Key] = {}  # the face as added, under its key
        self.prefer: dict[Key, int | None] = {}  # 1: its winding as added faces against the input, 0: along it
        self.parent: dict[Key, Key] = {}
        self.parity: dict[Key, int] = {}  # 1: turned against its parent
        self.need: dict[Key, int | None] = {}  # per root: 1 where it must turn for its piece to face the input

    def find(self, key: Key) -> tuple[Key, int]:
        """(root of ``key``'s piece, 1 where ``key`` is turned against it); the path walked is pointed at the root."""
        path = []
        while self.parent[key] != key:
            path.append(key)
            key = self.parent[key]
        turned = 0
        for node in reversed(path):  # nearest the root first: each node's parity to the root
            turned ^= self.parity[node]
            self.parent[node], self.parity[node] = key, turned
        return key, turned

    def asked(self, face: Key, neighbours: list[tuple[Key, int, int]], prefer: int | None = None
              ) -> tuple[dict[Key, int], int | None, bool]:
        """For ``face`` (a, b, c) beside the selected ``neighbours`` (key, x, y: across edge x-y), the turning of
        ``face`` against each neighbour's root that agrees with it, the turning the input asks of ``face`` (its own
        ``prefer``, or its neighbours' pieces'), and whether no root asks both windings and the pieces it joins can
        all face the input."""
        out: dict[Key, int] = {}
        agree = True
        for key, x, y in neighbours:
            root, turned = self.find(key)
            want = turned ^ _runs_down(self.wound[key], x, y) ^ _runs_down(face, x, y) ^ 1
            agree &= out.setdefault(root, want) == want
        side = prefer
        for root, want in out.items():
            need = self.need[root]
            if need is not None:  # the root turns by ``need``, the face by that and ``want``
                agree &= side is None or side == need ^ want
                side = need ^ want
        return out, side, agree

    def add(self, key: Key, face: Key, neighbours: list[tuple[Key, int, int]], prefer: int | None = None) -> None:
        """Take ``face`` under ``key``, its neighbours' pieces joined to it turned to agree with it (where two ask
        both windings of it, the first's)."""
        roots, side, _ = self.asked(face, neighbours, prefer)
        self.wound[key], self.prefer[key], self.parent[key], self.parity[key] = face, prefer, key, 0
        self.need[key] = side
        for root, want in roots.items():
            self.parent[root], self.parity[root] = key, want


class Selection:
    """The selected faces' bookkeeping: third vertices on each edge, and the angular sector each face
    covers around each of its corners in the tangent plane there (faces around a vertex must not
    overlap), and each face's normal.  A corner whose face lies farther than acos(``_CREASE``) from the
    vertex's tangent plane (across a crease or a corner the nearest points miss) has no sector there:
    see :meth:`_overlaps`.  ``open`` holds the boundary: each vertex's neighbours across an edge of
    one face, kept with ``third`` so that hole filling walks it without visiting every face at a vertex."""

    def __init__(self, vertices: np.ndarray, frames: np.ndarray, fold_angle: float):
        self.v = np.asarray(vertices, dtype=np.float64).tolist()
        fr = np.asarray(frames, dtype=np.float64)
        self.frames = fr.tolist()
        self.normals = np.cross(fr[:, 0], fr[:, 1]).tolist()
        self.min_cos = math.cos(math.radians(fold_angle))
        self.third: dict[tuple[int, int], list[int]] = {}
        self.sectors: dict[int, dict[tuple[int, int, int], tuple[float, float]]] = {}
        self.face_normals: dict[tuple[int, int, int], list[float]] = {}
        self.open: dict[int, set[int]] = {}
        self._windings, self._stale = Windings(), False

    def add_vertex(self, position: np.ndarray) -> None:
        """A vertex after the others (the closure's), with no tangent plane: its corners have no sector."""
        self.v.append([float(x) for x in position])
        self.frames.append([[math.nan] * 3, [math.nan] * 3])
        self.normals.append([math.nan] * 3)

    def _sector(self, a: int, b: int, c: int, f: list[float]) -> tuple[float, float]:
        """(start, width) in radians of the corner of face (a, b, c) (unit normal ``f``) at ``a``, seen in
        a's tangent plane; NaN where a has no tangent plane or the face lies across it."""
        n = self.normals[a]
        if not abs(f[0] * n[0] + f[1] * n[1] + f[2] * n[2]) >= _CREASE:  # also False with a NaN frame
            return (math.nan, math.nan)
        return _arc(self.v, a, b, c, self.frames[a])

    def _overlaps(self, a: int, b: int, c: int, n: list[float]) -> bool:
        """Whether the corner of face (a, b, c) (unit normal ``n``) at ``a`` overlaps a selected face's
        corner there.

        In a's tangent plane where both corners have a sector there; otherwise (a crease, a corner, a
        face across the plane) only a selected face nearly parallel to this one can overlap it, and the
        two are compared in this face's own plane.
        """
        s0, w0 = self._sector(a, b, c, n)
        own = None
        for key, (s1, w1) in self.sectors.get(a, {}).items():
            if not (math.isnan(s0) or math.isnan(s1)):
                if _arcs_overlap(s0, w0, s1, w1):
                    return True
                continue
            if own is None:
                e = [self.v[b][i] - self.v[a][i] for i in range(3)]
                k = sum(e[i] * n[i] for i in range(3))
                u = _unit([e[i] - k * n[i] for i in range(3)])
                frame = (u, _cross(n, u))
                own = (frame, _arc(self.v, a, b, c, frame))
            frame, (s2, w2) = own
            m = self.face_normals[key]
            if abs(n[0] * m[0] + n[1] * m[1] + n[2] * m[2]) < _PARALLEL:
                continue
            y, z = (x for x in key if x != a)
            if _arcs_overlap(s2, w2, *_arc(self.v, a, y, z, frame)):
                return True
        return False

    def fits(self, a: int, b: int, c: int, prefer: int | None = None) -> bool:
        """Face (a, b, c) keeps every edge in at most two faces, folds onto no neighbour across an
        edge, overlaps no selected face around any of its corners, and leaves every piece one that can be wound
        one way facing the input (:class:`Windings`; ``prefer``: 1 where (a, b, c) as wound faces against the
        input, 0 along it, None where the input does not say)."""
        for x, y, z in ((a, b, c), (b, c, a), (a, c, b)):
            others = self.third.get((x, y) if x < y else (y, x), ())
            if len(others) >= 2 or any(_folded(self.v, x, y, o, z, self.min_cos) for o in others):
                return False
        n = _normal(self.v, a, b, c)  # the same for every corner: they turn the same way
        if any(self._overlaps(x, y, z, n) for x, y, z in ((a, b, c), (b, c, a), (c, a, b))):
            return False
        return self.windings().asked((a, b, c), self._neighbours(a, b, c), prefer)[2]

    def _neighbours(self, a: int, b: int, c: int) -> list[tuple[Key, int, int]]:
        """The selected faces across each edge of face (a, b, c): (key, x, y) for edge x-y."""
        own = tuple(sorted((a, b, c)))
        out = []
        for x, y in ((a, b), (b, c), (a, c)):
            for o in self.third.get((x, y) if x < y else (y, x), ()):
                key = tuple(sorted((x, y, o)))
                if key != own:
                    out.append((key, x, y))
        return out

    def windings(self) -> Windings:
        """The faces' winding classes (:class:`Windings`), built again from the faces left after a removal."""
        if self._stale:
            old, self._windings, self._stale = self._windings, Windings(), False
            for key, face in old.wound.items():
                self._windings.add(key, face, [n for n in self._neighbours(*face) if n[0] in self._windings.wound],
                                   old.prefer.get(key))
        return self._windings

    def _edge_count_changed(self, x: int, y: int, n: int) -> None:
        """Edge (x, y) is now in ``n`` faces: on the boundary exactly when n is 1."""
        if n == 1:
            self.open.setdefault(x, set()).add(y)
            self.open.setdefault(y, set()).add(x)
        else:
            self.open.get(x, set()).discard(y)
            self.open.get(y, set()).discard(x)

    def add(self, a: int, b: int, c: int, prefer: int | None = None) -> None:
        key = tuple(sorted((a, b, c)))
        if self._stale:  # taken in when the classes are built again
            self._windings.wound[key], self._windings.prefer[key] = (a, b, c), prefer
        else:
            self._windings.add(key, (a, b, c), self._neighbours(a, b, c), prefer)
        for x, y, z in ((a, b, c), (b, c, a), (a, c, b)):
            others = self.third.setdefault((x, y) if x < y else (y, x), [])
            others.append(z)
            self._edge_count_changed(x, y, len(others))
        key = tuple(sorted((a, b, c)))  # any winding of the face names it
        n = self.face_normals[key] = _normal(self.v, a, b, c)
        for x, y, z in ((a, b, c), (b, c, a), (c, a, b)):
            self.sectors.setdefault(x, {})[key] = self._sector(x, y, z, n)

    def remove(self, a: int, b: int, c: int) -> None:
        for x, y, z in ((a, b, c), (b, c, a), (a, c, b)):
            others = self.third[(x, y) if x < y else (y, x)]
            others.remove(z)
            self._edge_count_changed(x, y, len(others))
        key = tuple(sorted((a, b, c)))
        del self.face_normals[key]
        self._windings.wound.pop(key, None)
        self._windings.prefer.pop(key, None)
        self._stale = True
        for x in (a, b, c):
            del self.sectors[x][key]
