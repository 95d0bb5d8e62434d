"""Open piecewise-planar inputs rebuilt exactly: a ramp, a roof without its floor, a box without its lid.

``planar.polyhedron`` rebuilds a closed polyhedron: every face of a plane ends where a neighbouring plane cuts
it.  An open surface has edges no plane ends: where the surface stops.  A game prop's open side almost always lies
on a side of its bounding box (the floor under a ramp, the top of a tray), so that side stands in as a plane with
no points: it bounds the faces of the planes that reach it and gets no face of its own.  The result is kept only
where every open edge lies on such a side and the surface and the points explain each other both ways, as for a
closed one; anything else gives None.

An input the pipeline has found open (``closure.decide_closed``) may also stop inside its box, as artists build
flat props from sheets: a fin or a flange that ends in the air, a board short of a shelf's opening, a panel set into
a frame that ends on the frame's walls.  With ``free`` each plane's faces end where its own points stop
(:func:`_stop_lines`: along or across the line of one of its neighbours, along a side of the box in a frame along
the shape's walls, or along a straight stretch of its own outline), every open edge must be where the points reach
and stop (:func:`_stops`), and a sheet that ends on a wall shares no edge with it (``detach.detached``), so that every
edge keeps at most two faces.
"""

from __future__ import annotations

from functools import partial

import numpy as np
from scipy.spatial import cKDTree

from .arrangement import MEETING_DEGREES
from .detach import detached
from .outline_edges import outline_ways
from .planar import PlanarConfig, _explains, planar_mesh
from .windings import agreeing

# A side of the box or a line across a sheet this near parallel to a plane does not cut it (its neighbours, which
# meet it by ``arrangement.meeting_sine``, always do).
PARALLEL_COS = np.cos(np.radians(MEETING_DEGREES))
PARALLEL_SINE = np.sin(np.radians(MEETING_DEGREES))
EDGE_SHARE = 0.3  # a plane's open edge spans at least this share of the plane's width along it
# A line where a sheet stops (``_stop_lines``) that lies within ALIKE cover radii of a side of the box or of another's
# plane is that plane (the points' furthest on each sheet lie a fraction of their spacing short of the edge they
# share; two boards of a shelf stop a radius or more apart).  Lines within this angle of each other run alike.
ALIKE_COS = np.cos(np.radians(2))
ALIKE = 0.25
# A frame is along the shape's walls where one of its planes lies within half a degree of an axis: an artist's frame
# and the canonical one (``canonical.canonical_rotation``) hold them within a hundredth of a degree; a small plane a
# degree or two off an axis in a turned frame lies so by chance.
ALIGNED_COS = np.cos(np.radians(0.5))
# A scan's sheets (its plane tolerance widened to its noise, ``planar``) stop and meet within this many tolerances
# of where their lines are: the least of the distances above in a free mode's checks.
NOISE_TOLERANCES = 2.0
# With ``free`` an open edge is kept where the points reach it and stop: at PROBES places along it their nearest point
# lies within REACHED cover radii on average (on the framed panels and shelves of ``benchmarks/open_sheets.py``
# 0.1-0.4; a face a side of the box cut off a radius past its points: 1.0 and more), and none within half a radius
# of where its face's plane goes on BEYOND radii past it (a plane that goes on past it has points about a third of a
# radius from there).
BEYOND = 1.0
PROBES = 8
REACHED = 0.6


def open_polyhedron(points: np.ndarray, normals: np.ndarray, cfg: PlanarConfig = PlanarConfig(), free: bool = False
                    ) -> tuple[np.ndarray, np.ndarray] | None:
    """The open piecewise-planar surface of an oriented point cloud whose open edges lie on its bounding box's
    sides (with ``free``, or where its points stop), or None where it is not one.

    Parameters
    ----------
    points : (N, 3) float, in the unit frame (``shape.Normalization``), the open sides along its axes
    normals : (N, 3) float, unit, on the side the faces face
    cfg : tolerances, as ``planar.polyhedron``
    free : bool
        Whether an open edge may also lie inside the box, where the points stop (see the module).

    Returns
    -------
    (V, 3) float64 vertices and (F, 3) int64 faces, edge-manifold and consistently oriented, with at least one
    open edge and every open edge on a side of the points' bounding box (or where they stop); or None.
    """
    made = planar_mesh(points, normals, cfg, cut=partial(_cut_at_box, free=free, exact=cfg.tolerance))
    if made is None:
        return None
    vertices, faces, pts, reach, sides, tolerance = made
    if free:
        vertices, faces = detached(vertices, faces, cfg.tolerance, reach)
    # Each plane's faces are wound by its points' normals; a scan's are signed only where its points enclose a
    # volume (``orientation.outward``), so one wall of a frame open at the back may face into the frame.  The
    # surface's own edges say which way its faces wind, and most of its area which side it faces.
    faces = agreeing(vertices, faces)
    stops = _stops(pts, reach, tolerance - cfg.tolerance) if free else None
    if not _open_where_it_stops(vertices, faces, sides, cfg.tolerance, stops) or not _explains(vertices, faces, pts,
                                                                                                reach):
        return None
    return vertices, faces


def _cut_at_box(points: np.ndarray, planes: np.ndarray, labels: np.ndarray, near: list[dict[int, int]], reach: float,
                tolerance: float, free: bool = False, exact: float = PlanarConfig.tolerance
                ) -> tuple[np.ndarray | None, list[list[int]] | None]:
    """``planar.planar_mesh``'s ``cut``: the box sides no plane lies on, and for each plane those where it stops
    (``_open_sides``); with ``free``, for each plane the lines where its own points stop (``_stop_lines``), inside
    the box or on a side of it, each a plane across it, one plane for the lines that lie on one (``_shared``); for
    a scan (``tolerance`` at its noise wider than ``exact``), from each plane's points off its neighbours' lines
    (:func:`_off_lines`), read no finer than ``NOISE_TOLERANCES`` times the tolerance."""
    sides = box_sides(points, planes, labels, reach)
    if not free:
        if not len(sides):
            return None, None
        return sides, [_open_sides(planes[k], sides, planes[sorted(near[k])], points[labels == k], reach)
                       for k in range(len(planes))]
    # The box's sides count only in a frame along the shape's walls: in a frame it is turned in, a side touches the
    # shape at a corner, at an angle to its edges.
    if not (np.abs(planes[:, :3]) > ALIGNED_COS).any():
        sides = sides[:0]
    # A scan (its tolerance wider than ``exact``'s) puts its points near a line two sheets meet on in either plane
    # within its tolerance: a sheet's points stop up to that short of the line and scatter that far about it, and a
    # strip of its neighbour's points runs on along the line past its own edges.
    scan = tolerance > exact
    gap = NOISE_TOLERANCES * tolerance if scan else 0.0
    found = []
    for k in range(len(planes)):
        # Neighbours it meets along the most first: of two directions a degree apart (a sheet folded a little,
        # one half along the wall, the other touching it at a corner), the line it runs along is taken.
        others = planes[sorted(near[k], key=lambda j: (-near[k][j], j))]
        own = points[labels == k]
        off = _off_lines(own, others, tolerance) if scan else None
        if off is not None and off.sum() >= 3:  # (a strip along its neighbours' lines keeps all of its points)
            own = own[off]
        distant = planes[[j for j in range(len(planes)) if j != k and j not in near[k]]]
        found.append(_stop_lines(planes[k], others, np.vstack([sides, distant]), own, reach, gap))
    owner = np.repeat(np.arange(len(planes)), [len(lines) for lines, _, _ in found])
    lines, spans, bands = (np.vstack([np.zeros((0, *shape)), *[x[i] for x in found]])
                           for i, shape in enumerate(((4,), (2, 3), (4,))))
    sides, which = _shared(sides, lines, spans, bands, planes[owner], reach, gap)
    return sides, [sorted(set(which[owner == k].tolist())) for k in range(len(planes))]


def _off_lines(points: np.ndarray, others: np.ndarray, tolerance: float) -> np.ndarray:
    """(P,) whether each of a plane's ``points`` (P, 3) lies farther than ``tolerance`` from every plane of ``others``
    (K, 4), its neighbours: off the lines where it meets them."""
    return (np.abs(points @ others[:, :3].T - others[:, 3]) > tolerance).all(1)


def _shared(sides: np.ndarray, lines: np.ndarray, spans: np.ndarray, bands: np.ndarray, sheets: np.ndarray,
            reach: float, gap: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The box ``sides`` (S, 4) and the planes of ``lines`` (L, 4; each across its sheet of ``sheets`` (L, 4)), a line
    made one with a side or a line before it that crosses its sheet and holds both ends of its ``spans`` (L, 2, 3)
    within ``ALIKE`` x ``reach`` or ``gap`` (the front edges of a shelf's walls all stop at its opening; a flange
    and a sloping wall both stop on the box's floor): (S + M, 4) planes, the sides first, and (L,) which one each line
    became.  Corners where two such sheets meet then come from the same planes.  A plane made of lines facing alike
    lies where all their points put the edge (``bands`` (L, 4): each line's furthest point and band, ``_edge``)."""
    out, pooled = list(sides), {}
    which = np.zeros(len(lines), dtype=np.int64)
    for i, (line, ends, band, sheet) in enumerate(zip(lines, spans, bands, sheets, strict=True)):
        off = np.array([np.abs(ends @ o[:3] - o[3]).max() if abs(o[:3] @ sheet[:3]) < PARALLEL_COS else np.inf
                        for o in out]).reshape(-1)
        if not len(off) or off.min() >= max(ALIKE * reach, gap):
            out.append(line.copy())
            off = np.r_[off, 0.0]
        j = which[i] = int(off.argmin())  # the nearest: a line on a box's edge lies on two sides
        if j >= len(sides) and out[j][:3] @ line[:3] > ALIKE_COS:
            pooled.setdefault(j, []).append(band)
            b = np.array(pooled[j])
            out[j][3] = _edge(float((b[:, :3] @ out[j][:3]).max()), int(b[:, 3].sum()), reach)
    return np.array(out).reshape(-1, 4), which


def _stop_lines(plane: np.ndarray, neighbours: np.ndarray, sides: np.ndarray, points: np.ndarray, reach: float,
                gap: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(L, 4) planes across ``plane`` (each at right angles to it) along the lines where its ``points`` stop: a board
    short of a shelf's opening, a ledge standing out of a wall, a wall at its box's open side, a flange ending in the
    air; (L, 2, 3) the ends of the stretch of each the points follow; (L, 4) the points' furthest across each and how
    many lie within ``reach`` of it across the line (:func:`_edge`).  An artist's sheet mostly ends along a line
    parallel or at right angles to one of its other edges, or along a side of its box; else (a gusset's slope, a
    plate's slanted end) along a straight stretch of its own outline.  So each line runs along or across the line of
    one of its ``neighbours`` (K, 4), along the line of one of ``sides`` (S, 4: the box's, and the shape's planes
    that do not meet it, as the ground under a sign standing apart), or along a direction of
    the points' outline (``outline_edges.outline_ways``) 10 degrees off every line kept before it (a board cut a few
    degrees off square: its neighbour's direction is not followed, its outline's is), at the points' furthest
    across it; it is kept where the points follow it (:func:`_followed`) and the stretch they follow lies on no
    neighbour's line (where a real edge ends the plane) nor a line kept before (:func:`_lies_on`); ``gap``: the
    least distance those checks read as near (a scan's noise).
    """
    n = plane[:3]
    out: list[np.ndarray] = []
    spans: list[np.ndarray] = []
    bands: list[np.ndarray] = []
    ways: list[np.ndarray] = []
    for i, other in enumerate(np.vstack([neighbours, sides])):
        u = np.cross(n, other[:3])
        if i >= len(neighbours) and np.linalg.norm(u) < PARALLEL_SINE:
            continue
        u /= np.linalg.norm(u)
        along = np.cross(n, u)  # the edge along the other's line; across it (at right angles) for a neighbour
        # A side's direction a degree or two off a neighbour's is the canonical frame's rounding: the artist's is
        # the neighbour's.
        ways.extend(w for w in ((along, -along, u, -u) if i < len(neighbours) else (along, -along))
                    if all(w @ o < ALIKE_COS for o in ways))
    # A sheet cut at any angle (a gusset's slope, a plate's slanted end) stops along its own outline's direction,
    # tried after the neighbours' and the sides' (an outline fitted to an artist's edge a degree off its neighbour's
    # direction gives way to it where that line is kept).
    first = len(ways)
    ways += [w for w in outline_ways(points, n, reach, ALIKE_COS) if all(w @ o < ALIKE_COS for o in ways)]
    for i, w in enumerate(ways):
        if i >= first and any(w @ o[:3] > PARALLEL_COS for o in out):
            continue
        across = points @ w
        band = int((across > across.max() - reach).sum())
        line = np.r_[w, _edge(across.max(), band, reach)]
        span = _followed(points, line, n, reach, gap)
        if span is not None and not _lies_on(n, span, np.vstack([neighbours, *out]), reach, gap):
            out.append(line)
            spans.append(span)
            bands.append(np.r_[points[across.argmax()], band])
    return np.array(out).reshape(-1, 4), np.array(spans).reshape(-1, 2, 3), np.array(bands).reshape(-1, 4)


def _edge(furthest: float, band: int, reach: float) -> float:
    """Where an edge lies across its line's normal, from its points' ``furthest`` across it and the ``band`` of
    points within ``reach`` of that: uniform samples end short of their edge by about the band's width over its
    points."""
    return furthest + reach / max(band, 1)


def _lies_on(n: np.ndarray, ends: np.ndarray, others: np.ndarray, reach: float, gap: float = 0.0) -> bool:
    """Whether both ``ends`` (2, 3), in the plane of normal ``n`` (3,), lie near the line where it meets one of
    ``others`` (K, 4; planes that meet it: its neighbours and lines across it): within ``reach`` of it (in that
    plane) where that line runs at an angle to theirs (the points' furthest across a direction a few degrees off an
    edge only touch that edge), within ``ALIKE`` x ``reach`` where it runs along it within ``ALIKE_COS`` (a panel set
    back from an open side a little: the walls go on past it); within ``gap`` at least."""
    cross = np.cross(n, others[:, :3])
    sine = np.linalg.norm(cross, axis=1)
    crossing = sine > 0
    off = np.abs(ends @ others[crossing, :3].T - others[crossing, 3]) / sine[crossing]  # (2, K)
    d = (ends[1] - ends[0]) / np.linalg.norm(ends[1] - ends[0])
    alike = np.abs(cross[crossing] @ d) / sine[crossing] > ALIKE_COS
    return bool((off < np.maximum(np.where(alike, ALIKE, 1.0) * reach, gap)).all(0).any())


def _followed(points: np.ndarray, line: np.ndarray, n: np.ndarray, reach: float, gap: float = 0.0
              ) -> np.ndarray | None:
    """(2, 3) the ends of the stretch of ``line`` (4,; a plane across the plane of normal ``n`` (3,) that the
    ``points`` lie on, its normal pointing away from them) along which they stop, or None: those within ``reach`` of
    it span ``EDGE_SHARE`` of the points' width along it at least, and come within half a ``reach`` (or ``gap``) of it
    in the first and the last quarter of that span, not only where the line touches a corner of the points at an
    angle to their edge."""
    u = np.cross(n, line[:3])
    u /= np.linalg.norm(u)
    off = line[3] - points @ line[:3]
    band = off < reach
    along = points[band] @ u
    if band.sum() < 3 or np.ptp(along) < max(EDGE_SHARE * np.ptp(points @ u), reach):
        return None
    quarter = np.minimum(((along - along.min()) / np.ptp(along) * 4).astype(int), 3)
    if not (np.bincount(quarter, off[band] < max(0.5 * reach, gap), minlength=4)[[0, 3]] > 0).all():
        return None  # (a stretch may have gaps: legs standing on one line)
    ends = points[band][[along.argmin(), along.argmax()]]
    return ends + np.outer(line[3] - ends @ line[:3], line[:3])  # onto the line, in the points' plane


def box_sides(points: np.ndarray, planes: np.ndarray, labels: np.ndarray, reach: float) -> np.ndarray:
    """(S, 4) the sides of the points' axis-aligned bounding box (outward normal n, offset d: n.x = d) that no
    plane of ``planes`` (K, 4) lies on: where an open surface may stop.  A plane lies on a side where it is parallel
    to it and its own points (``labels``, (N,) the plane of each point) reach it within a quarter of ``reach``: a
    panel set a little back from an open side stays off it."""
    lo, hi = points.min(0), points.max(0)
    reached = np.full((len(planes), 6), -np.inf)  # each plane's points' furthest along each side's normal, less d
    for k in range(len(planes)):
        own = points[labels == k]
        if len(own):
            reached[k] = np.r_[lo - own.min(0), own.max(0) - hi][[0, 3, 1, 4, 2, 5]]
    out = []
    for axis in range(3):
        for sign, at in ((-1.0, lo[axis]), (1.0, hi[axis])):
            n = np.zeros(3)
            n[axis] = sign
            side = 2 * axis + (sign > 0)
            on = (np.abs(planes[:, :3] @ n) > PARALLEL_COS) & (reached[:, side] > -0.25 * reach)
            if not on.any():
                out.append(np.r_[n, sign * at])
    return np.array(out).reshape(-1, 4)


def _open_sides(plane: np.ndarray, sides: np.ndarray, neighbours: np.ndarray, points: np.ndarray, reach: float
                ) -> list[int]:
    """The indices of the box ``sides`` (S, 4) where a plane's surface stops: those it is not parallel to whose
    line its ``points`` follow across ``EDGE_SHARE`` of the plane's width at least (not a corner touching the
    side, as a gable's apex), where that line does not run along a real edge instead (a ridge touching the box:
    along the line where it meets one of its ``neighbours`` (K, 4)) nor along a side already taken (an eave on a
    box's edge reaches two sides: the one crossing the plane more steeply is taken)."""
    order = np.argsort(-np.linalg.norm(np.cross(plane[:3], sides[:, :3]), axis=1))
    taken: list[int] = []
    for j in order:
        side = sides[j]
        if abs(plane[:3] @ side[:3]) > PARALLEL_COS:
            continue
        at = points[np.abs(points @ side[:3] - side[3]) < reach]
        u = np.cross(plane[:3], side[:3])
        if len(at) < 3 or np.ptp(at @ u) < max(EDGE_SHARE * np.ptp(points @ u), reach * np.linalg.norm(u)):
            continue
        others = np.vstack([neighbours, sides[taken]])
        if len(others) and _along(plane, side, at.mean(0), others, reach):
            continue
        taken.append(int(j))
    return taken


def _along(plane: np.ndarray, side: np.ndarray, near: np.ndarray, others: np.ndarray, reach: float) -> bool:
    """Whether the line where ``plane`` meets ``side`` runs along the line where it meets one of ``others`` (K, 4):
    within 10 degrees of it and, at the point of the line nearest ``near`` (3,), within ``reach`` of it."""
    n = plane[:3]
    u = np.cross(n, side[:3])
    u /= np.linalg.norm(u)
    p = np.linalg.solve(np.array([n, side[:3], u]), np.array([plane[3], side[3], u @ near]))
    w = np.cross(n, others[:, :3])
    sine = np.linalg.norm(w, axis=1)
    parallel = np.linalg.norm(np.cross(u, w / np.maximum(sine, 1e-12)[:, None]), axis=1) < PARALLEL_SINE
    return bool((parallel & (np.abs(others[:, :3] @ p - others[:, 3]) < reach * sine)).any())


def _open_where_it_stops(vertices: np.ndarray, faces: np.ndarray, sides: np.ndarray, tol: float, stops=None) -> bool:
    """Whether ``faces`` are edge-manifold and consistently oriented, with open edges, each on one of ``sides`` or,
    given ``stops`` (:func:`_stops`), where the points stop."""
    e = np.c_[faces.ravel(), faces[:, [1, 2, 0]].ravel()]
    if len(np.unique(e, axis=0)) != len(e):
        return False
    edges, count = np.unique(np.sort(e, axis=1), axis=0, return_counts=True)
    if (count > 2).any() or not (count == 1).any():
        return False
    if stops is not None:  # every open edge, on a side or not: a side the points do not reach cuts nothing
        key = np.sort(e, axis=1) @ [len(vertices), 1]
        rows = np.nonzero(np.isin(key, edges[count == 1] @ [len(vertices), 1]))[0]  # row r: a side of face r // 3
        return stops(vertices, faces[rows // 3], e[rows])
    ends = vertices[edges[count == 1]]  # (B, 2, 3)
    off = np.abs(ends @ sides[:, :3].T - sides[:, 3])  # (B, 2, S)
    return bool((off.max(1) < tol).any(1).all())


def _stops(points: np.ndarray, reach: float, noise: float = 0.0):
    """``stops(vertices, f, edges)``: whether the ``points`` (N, 3) reach and stop at every one of ``edges`` (E, 2),
    each an open edge as its face of ``f`` (E, 3) winds it: at ``PROBES`` places along it, their nearest within
    ``REACHED`` x ``reach`` on average (and ``noise`` more: a scan's furthest point, which places the edge, lies
    that much beyond the others), and none within half a ``reach`` of where its face's plane goes ``BEYOND`` x
    ``reach`` past it, but at its two end places (a short edge ending on a wall has the wall's points there)."""
    tree = cKDTree(points)

    def stops(vertices: np.ndarray, f: np.ndarray, edges: np.ndarray) -> bool:
        a, b = vertices[edges[:, 0]], vertices[edges[:, 1]]
        n = np.cross(vertices[f[:, 1]] - vertices[f[:, 0]], vertices[f[:, 2]] - vertices[f[:, 0]])
        out = np.cross(b - a, n)  # in the face's plane, away from it: the face winds counter-clockwise about n
        out /= np.linalg.norm(out, axis=1, keepdims=True)
        t = (np.arange(PROBES) + 0.5) / PROBES
        on = (a[None] + t[:, None, None] * (b - a)[None]).reshape(-1, 3)  # (PROBES * E, 3), probe by probe
        out = np.tile(out, (PROBES, 1))
        reached = tree.query(on)[0].reshape(PROBES, -1).mean(0)
        beyond = tree.query(on + BEYOND * reach * out)[0].reshape(PROBES, -1)[1:-1]
        return bool((reached < REACHED * reach + noise).all() and (beyond > 0.5 * reach).all())

    return stops
