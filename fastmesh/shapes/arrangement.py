"""The line arrangement of one plane (:mod:`.planar`): the planes that meet it, convex cells cut by their lines,
which of them the plane's own points cover, and the outline of the covered ones."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

MEETING_DEGREES = 10.0  # planes closer to parallel than this meet only where their line is sure (``meeting_sine``)
# A line placed where a sheet's points stop is sure to about this share of a cover radius (``snapped``): at half a
# radius two walls' bottom corners of a house without its floor, each placed on its own wall's line, moved to their
# middle and one came out further off (``benchmarks/shallow_folds.py``).
PLACED_SNAP = 0.35


class Cell:
    """A convex cell of a plane's line arrangement: (m, 2) corners counter-clockwise, and for each the line its
    edge to the next corner lies on (a plane's index; -1 for the box around the points)."""

    def __init__(self, corners: np.ndarray, lines: list[int]):
        self.corners, self.lines = corners, lines

    @classmethod
    def box(cls, lo: np.ndarray, hi: np.ndarray) -> Cell:
        return cls(np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]]), [-1] * 4)

    def split(self, line: int, normal: np.ndarray, offset: float) -> list[Cell]:
        """The parts of the cell on either side of ``normal . x = offset`` (those with area)."""
        side = self.corners @ normal - offset
        side = np.where(np.abs(side) < 1e-12, 0.0, side)
        if (side >= 0).all() or (side <= 0).all():  # the line misses the cell (or runs along an edge)
            return [self]
        parts = [self._keep(sign * side, line) for sign in (1.0, -1.0)]
        return [p for p in parts if p is not None and p.area() > 1e-14]

    def _keep(self, side: np.ndarray, line: int) -> Cell | None:
        """The part where ``side`` (signed distances of the corners) is not negative (Sutherland-Hodgman)."""
        corners, lines = [], []
        for i in range(len(side)):
            j = (i + 1) % len(side)
            a, b = side[i], side[j]
            cut = self.corners[i] + a / (a - b) * (self.corners[j] - self.corners[i]) if a * b < 0 else None
            if a > 0:
                corners.append(self.corners[i])
                lines.append(self.lines[i])
                if b < 0:
                    corners.append(cut)
                    lines.append(line)
            elif a == 0:
                corners.append(self.corners[i])
                lines.append(self.lines[i] if b > 0 else line)
            elif b > 0:
                corners.append(cut)
                lines.append(self.lines[i])
        return Cell(np.array(corners), lines) if len(corners) >= 3 else None

    def count(self, points: np.ndarray) -> int:
        """How many of the (N, 2) points lie inside the cell."""
        edge = np.roll(self.corners, -1, axis=0) - self.corners
        rel = points[:, None, :] - self.corners[None]
        return int(((edge[None, :, 0] * rel[..., 1] - edge[None, :, 1] * rel[..., 0]) >= 0).all(1).sum())

    def area(self) -> float:
        return signed_area(self.corners)


def chosen(cells: list[Cell], flat: np.ndarray, spacing: float) -> np.ndarray:
    """(C,) which cells the plane's face covers.  A cell large enough to hold six points at the points' density
    is in where it holds half of them; a smaller one (a sliver where lines cross near a corner) sides with the
    decided cells it shares most edge length with, so such slivers never add corners of their own."""
    density = 7.67 / (np.pi * spacing**2)  # a disc holding 7.67 points (Poisson) has the 8th neighbour's radius
    state = np.full(len(cells), -1)
    for i, c in enumerate(cells):
        expected = density * c.area()
        if expected >= 6:
            state[i] = int(c.count(flat) >= 0.5 * expected)
    shared = _shared_lengths(cells)
    while (state < 0).any():
        vote = {i: sum(length * (1 if state[j] else -1) for j, length in shared[i].items() if state[j] >= 0)
                for i in np.nonzero(state < 0)[0]}
        decided = {i: v for i, v in vote.items() if v != 0}
        if not decided:
            break
        for i, v in decided.items():
            state[i] = int(v > 0)
    return state == 1


def _shared_lengths(cells: list[Cell]) -> list[dict[int, float]]:
    """For each cell, the length of edge it shares with each other cell."""
    ids, allc = _corner_ids(cells)
    owner, start = {}, 0
    for i, c in enumerate(cells):
        k = len(c.corners)
        for e in range(k):
            owner[(int(ids[start + e]), int(ids[start + (e + 1) % k]))] = (i, float(
                np.linalg.norm(allc[start + (e + 1) % k] - allc[start + e])))
        start += k
    shared: list[dict[int, float]] = [{} for _ in cells]
    for (a, b), (i, length) in owner.items():
        if (b, a) in owner:
            j = owner[(b, a)][0]
            shared[i][j] = shared[i].get(j, 0.0) + length
    return shared


def _corner_ids(cells: list[Cell]) -> tuple[np.ndarray, np.ndarray]:
    """The corners of all cells stacked, (N, 2), and (N,) one id per distinct point."""
    allc = np.vstack([c.corners for c in cells])
    return merge_points(allc, 1e-9)[1], allc


def outline(cells: list[Cell], keep: np.ndarray) -> list[list[tuple[np.ndarray, int]]] | None:
    """The boundary of the union of the ``keep`` cells of a line arrangement: rings of (2D corner, line of the
    edge that leaves it), outer rings counter-clockwise and holes clockwise.  Adjacent cells of a line arrangement
    share whole edges, so the boundary is the set of edges only one kept cell has.  None where two rings touch
    at a corner."""
    ids, allc = _corner_ids(cells)
    edges, start = {}, 0
    for c, kept in zip(cells, keep, strict=True):
        k = len(c.corners)
        mine = ids[start:start + k]
        for i in range(k):
            a, b = int(mine[i]), int(mine[(i + 1) % k])
            if kept and a != b:
                edges[(a, b)] = (allc[start + i], c.lines[i])
        start += k
    leaving: dict[int, tuple[int, np.ndarray, int]] = {}
    for (a, b), (point, line) in edges.items():
        if (b, a) in edges:
            continue
        if a in leaving:  # two boundary edges leave one corner: rings touching there
            return None
        leaving[a] = (b, point, line)
    rings = []
    while leaving:
        a = next(iter(leaving))
        ring = []
        while a in leaving:
            b, point, line = leaving.pop(a)
            ring.append((point, line))
            a = b
        rings.append(ring)
    return rings


def merge_points(points: np.ndarray, eps: float) -> tuple[np.ndarray, np.ndarray]:
    """(N, d) points -> (M, d) distinct ones (those within ``eps`` of each other, chained, as their mean) and (N,)
    the index of each (groups numbered by their first point)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    pairs = cKDTree(points).query_pairs(eps, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(points),) * 2)
    group = connected_components(graph, directed=False)[1]
    index = np.unique(group, return_index=True)[1].argsort().argsort()[group]  # in order of first appearance
    sums = np.zeros((index.max() + 1, points.shape[1]))
    np.add.at(sums, index, points)
    return sums / np.bincount(index)[:, None], index


def plane_basis(normal: np.ndarray) -> np.ndarray:
    """(3, 2) two unit vectors spanning the plane of ``normal`` (u x v = normal)."""
    u = np.cross(normal, [1.0, 0, 0] if abs(normal[0]) < 0.9 else [0, 1.0, 0])
    u /= np.linalg.norm(u)
    return np.c_[u, np.cross(normal, u)]


def neighbour_planes(points: np.ndarray, labels: np.ndarray, planes: np.ndarray, reach: float, tolerance: float
                     ) -> list[dict[int, int]]:
    """For each plane, the planes that meet it: not parallel (:func:`meeting_sine` at ``tolerance``), with points
    of both within ``reach`` of each other at three places or more; each with that count (their contact: the length
    they meet along, where a plane that only touches it at a corner counts a few)."""
    least = meeting_sine(tolerance, reach)
    pairs = cKDTree(points).query_pairs(reach, output_type="ndarray")
    a, b = labels[pairs[:, 0]], labels[pairs[:, 1]]
    keep = (a >= 0) & (b >= 0) & (a != b)
    found, count = np.unique(np.sort(np.c_[a[keep], b[keep]], axis=1), axis=0, return_counts=True)
    near: list[dict[int, int]] = [{} for _ in planes]
    for (i, j), c in zip(found, count, strict=True):
        if c >= 3 and np.linalg.norm(np.cross(planes[i, :3], planes[j, :3])) > least:
            near[i][int(j)] = near[j][int(i)] = int(c)
    return near


def meeting_sine(tolerance: float, reach: float) -> float:
    """The least sine of the angle between two planes that meet along a line: a plane's offset, sure to within
    ``tolerance``, moves their line by ``tolerance`` over the sine across it, and the line must be sure to within
    half the cover radius ``reach`` (exact data: planes a degree apart, a low roof's or a thin wedge's), and
    never finer than ``MEETING_DEGREES`` (a scan)."""
    return min(np.sin(np.radians(MEETING_DEGREES)), 2 * tolerance / reach)


def snapped(corners: np.ndarray, meets: np.ndarray, placed: int, radius: float) -> np.ndarray:
    """(N, 3) ``corners`` with each one whose lines include a placed plane (an index ``placed`` or more: a line
    where a sheet's points stop, a side of their box) moved onto a corner within ``radius`` that lies on the same
    two other planes and on fewer placed ones (to the middle of the two where they are alike), nearest pairs first.
    ``meets`` (N, 3): each corner's face plane, then the two planes whose lines cross there.  Both lie on the line
    of the two planes they share, so a corner that moves along it stays on its face's plane."""
    out = np.array(corners, dtype=np.float64)
    count = (meets >= placed).sum(1)
    pairs = cKDTree(out).query_pairs(radius, output_type="ndarray")
    pairs = pairs[np.argsort(np.linalg.norm(out[pairs[:, 0]] - out[pairs[:, 1]], axis=1), kind="stable")]
    moved = np.zeros(len(out), dtype=bool)
    for i, j in pairs:
        own = set(meets[i].tolist()), set(meets[j].tolist())
        shared = own[0] & own[1]
        if len(shared) != 2 or min(map(len, own)) < 3 or moved[i] or moved[j]:
            continue
        # Which may move: a corner whose face plane is on the shared line and whose third plane is placed.
        free = [c for c, mine in zip((i, j), own, strict=True)
                if meets[c, 0] in shared and max(mine - shared) >= placed]
        if count[i] != count[j]:
            free = [c for c in free if count[c] == max(count[i], count[j])]
        if not free:
            continue
        target = out[[i, j]].mean(0) if len(free) == 2 else out[j if free[0] == i else i]
        out[free] = target
        moved[free] = True
    return out


def signed_area(flat: np.ndarray) -> float:
    """The area of a polygon (m, 2) by the shoelace formula: positive wound counter-clockwise."""
    x, y = flat.T
    return 0.5 * float(x @ np.roll(y, -1) - y @ np.roll(x, -1))


def inside_ring(point: np.ndarray, ring: np.ndarray) -> bool:
    """Whether a 2D point lies inside a ring (even-odd rule)."""
    x, y = ring.T
    x2, y2 = np.roll(x, -1), np.roll(y, -1)
    crosses = (y > point[1]) != (y2 > point[1])
    at = x + (point[1] - y) * (x2 - x) / np.where(y2 == y, 1.0, y2 - y)
    return bool(np.sum(crosses & (point[0] < at)) % 2)
