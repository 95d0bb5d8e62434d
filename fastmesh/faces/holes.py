"""Closing the holes of a selected surface: boundary loops, ear clipping, whole-loop triangulation,
and the repair that takes out the faces blocking a hole.

Every face added here lies on the input surface (support distance at most the limit) and fits the
selection's bookkeeping (:class:`fastmesh.faces.selection.Selection`): a closed input gives a
closed result where its holes allow, an open input stays open.
"""

from __future__ import annotations

import itertools

import numpy as np
from scipy.spatial import cKDTree

from .meshops import distinct_corners, face_sides
from .selection import Selection
from .support import SupportCache

# Rings of faces around a hole that :func:`fill_holes` may take out to close it.
REPAIR_RINGS = 2
# Loops of up to this many edges that ear clipping cannot close are triangulated as a whole
# (:func:`_best_triangulation` weighs all C(k, 3) triangles of a k-loop).
WHOLE_LOOP_MAX = 16


def boundary_loops(faces: np.ndarray) -> list[list[int]]:
    """Closed loops of the edges that have one face (vertex lists, unclosed).

    Loops are walked on the undirected boundary edges, so faces that cannot be oriented
    consistently still give their loops; where several loops meet at a vertex the walk takes the
    first free edge.  Open chains (possible only with edges in three faces) are left out.
    """
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    e = np.sort(face_sides(f), axis=1)
    uniq, cnt = np.unique(e, axis=0, return_counts=True)
    return _walk_loops(uniq[cnt == 1].tolist())


def _loops_through(book: Selection, seeds) -> list[list[int]]:
    """The loops :func:`boundary_loops` finds in the selected faces (``book``) on the boundary edges
    connected to the edges ``seeds``, in the same order, found from the seeds outward (a repair
    looks at one hole; walking the whole mesh's boundary for each would cost most of the stage).

    The same loops: the walk of :func:`boundary_loops` never crosses from one connected set of
    boundary edges to another, and on a subset of whole sets it meets their vertices in the same
    relative order.
    """
    stack = [x for e in seeds if len(book.third.get(e, ())) == 1 for x in e]
    seen, found = set(), set()
    while stack:
        x = stack.pop()
        if x in seen:
            continue
        seen.add(x)
        for y in book.open.get(x, ()):
            e = (x, y) if x < y else (y, x)
            if e not in found:
                found.add(e)
                stack.append(y)
    return _walk_loops(sorted(found))


def _walk_loops(edges: list) -> list[list[int]]:
    """Loops of boundary edges (``edges``: [a, b] with a < b, in lexicographic order); see
    :func:`boundary_loops`."""
    nbr: dict[int, list[int]] = {}
    for a, b in edges:
        nbr.setdefault(a, []).append(b)
        nbr.setdefault(b, []).append(a)
    loops = []
    while nbr:
        start = next(iter(nbr))
        loop, cur = [start], start
        while True:
            succ = nbr[cur].pop()
            nbr[succ].remove(cur)
            for x in (cur, succ):
                if not nbr[x]:
                    del nbr[x]
            if succ == start or succ not in nbr:
                break
            loop.append(succ)
            cur = succ
        if succ == start:
            loops.extend(x for x in _simple_loops(loop) if len(x) >= 3)
    return loops


def _simple_loops(loop: list[int]) -> list[list[int]]:
    """Split a closed vertex walk at repeated vertices (two holes touching at a vertex) into simple loops."""
    out, stack, at = [], [], {}
    for x in loop:
        if x in at:  # the walk since x's last visit is a loop of its own
            i = at[x]
            out.append(stack[i:])
            for y in stack[i + 1:]:
                del at[y]
            stack = stack[:i + 1]
        else:
            at[x] = len(stack)
            stack.append(x)
    out.append(stack)
    return out


def _clip_loop(loop: list[int], book: Selection, support: SupportCache,
               limit: float) -> list[tuple[int, int, int]] | None:
    """Ear clipping of one boundary loop, best-supported ear first (see :func:`fill_holes`).

    Returns the ears (already in ``book``), or None when some part of the loop cannot be closed
    (``book`` is then as before)."""
    poly, added = list(loop), []
    while len(poly) >= 3:
        k = len(poly)
        ears = np.array([[poly[i - 1], poly[i], poly[(i + 1) % k]] for i in range(k)])
        d = support(ears)
        placed = False
        for i in np.argsort(d, kind="stable"):
            if d[i] > limit:
                break
            a, b, c = ears[i].tolist()
            new_edge = (a, c) if a < c else (c, a)
            if (k > 3 and book.third.get(new_edge)) or not book.fits(a, b, c):
                continue
            book.add(a, b, c)
            added.append((a, b, c))
            poly.pop(int(i))
            placed = True
            break
        if not placed:
            for t in added:
                book.remove(*t)
            return None
    return added


def _cheapest_chains(k: int, cost: dict[tuple[int, int, int], float]) -> dict[tuple[int, int], tuple[float, int]]:
    """For each chord (i, j), i < j, of a k-loop that the triangles ``cost`` (index triple i < m < j ->
    cost) can close: the least total cost of triangulating the chain i..j and the apex m of its
    triangle on (i, j) (the least m among equal costs)."""
    apex: dict[tuple[int, int], list[int]] = {}
    for i, m, j in sorted(cost):
        apex.setdefault((i, j), []).append(m)
    best: dict[tuple[int, int], tuple[float, int]] = {}
    for span in range(2, k):
        for i in range(k - span):
            j = i + span
            options = [(cost[(i, m, j)] + (best[(i, m)][0] if m - i > 1 else 0.0)
                        + (best[(m, j)][0] if j - m > 1 else 0.0), m)
                       for m in apex.get((i, j), ())
                       if (m - i == 1 or (i, m) in best) and (j - m == 1 or (m, j) in best)]
            if options:
                best[(i, j)] = min(options)
    return best


def _best_triangulation(loop: list[int], book: Selection, support: SupportCache,
                        limit: float, folds: bool = False) -> list[tuple[int, int, int]] | None:
    """The triangulation of ``loop`` (no inner vertices) with the least total support distance, among
    triangles that lie on the surface, add no edge the selection already has, and fit it.

    Dynamic programming over the loop's sub-chains (hole filling after Liepa, 2003, weighted by
    support): ear clipping commits to the best ear first and can leave itself a last triangle that
    does not fit; this finds a way through whenever one exists among the triangles allowed alone.
    Returns the faces (added to ``book``), or None (``book`` unchanged) when there is none or its
    faces do not fit together.  With ``folds`` the faces are not checked against the selection's folds
    and overlaps, only against edges it already has (the closure's last step, ``closure.close_loops``)."""
    k = len(loop)
    allowed = _allowed_triangles(loop, book, support, limit) if k >= 3 else None
    if allowed is None:
        return None
    cost, face = allowed
    # The check against the selection is the costly part, and most loops that reach here have no
    # triangulation in the end: find the cheapest one among the triangles not yet known to fail it,
    # check only its faces, and look again without those that fail (the cheapest found with every
    # face passing is the cheapest among the triangles that pass: the others only ever lowered costs).
    checked = set()
    while True:
        best = _cheapest_chains(k, cost)
        if (0, k - 1) not in best:
            return None
        used, todo = [], [(0, k - 1)]
        while todo:
            i, j = todo.pop()
            m = best[(i, j)][1]
            used.append((i, m, j))
            todo += [c for c in ((i, m), (m, j)) if c[1] - c[0] > 1]
        failed = [] if folds else [x for x in used if x not in checked and not book.fits(*face[x])]
        if not failed:
            break
        checked.update(used)
        for x in failed:
            del cost[x]
    return _placed(book, [face[x] for x in used], folds)


def _allowed_triangles(loop: list[int], book: Selection, support: SupportCache, limit: float
                       ) -> tuple[dict, dict] | None:
    """The triangles of ``loop``'s vertices (k >= 3) a triangulation of it may use: on the surface (support
    distance within ``limit``), of three distinct vertices, adding no chord the selection already has.  Returns
    (index triple i < m < j -> support distance, index triple -> the triangle's vertices), or None where some
    loop edge lies in none of them (then the loop has no triangulation)."""
    k = len(loop)
    ijm = np.array(list(itertools.combinations(range(k), 3)), dtype=np.int64)  # i < m < j
    tris = np.asarray(loop, dtype=np.int64)[ijm]
    d = support(tris)
    # Every edge of the loop lies in exactly one face of a triangulation: one that no supported
    # triangle covers rules the loop out before any triangle is checked against the selection.
    lo, mid, hi = ijm.T
    # A loop that passes a vertex twice (``closure.hole_loops``) has triangles on both of its visits: not faces.
    on = (d <= limit) & distinct_corners(tris)
    covered = np.zeros(k, dtype=bool)  # edge (p, p + 1), and (k - 1, 0) as edge k - 1
    covered[lo[on & (mid == lo + 1)]] = True
    covered[mid[on & (hi == mid + 1)]] = True
    covered[k - 1] = bool((on & (lo == 0) & (hi == k - 1)).any())
    if not covered.all():
        return None
    # The chords of the loop that the selection already has (as a table over loop positions): no triangle
    # may add one.  A loop edge is no chord.
    taken = np.zeros((k, k), dtype=bool)
    for p, q in itertools.combinations(range(k), 2):
        if q - p != 1 and (p, q) != (0, k - 1):
            a, b = sorted((loop[p], loop[q]))
            taken[p, q] = bool(book.third.get((a, b)))
    on &= ~(taken[lo, mid] | taken[mid, hi] | taken[lo, hi])
    cost = dict(zip(map(tuple, ijm[on].tolist()), d[on].tolist(), strict=True))  # index triple -> support
    face = dict(zip(cost, map(tuple, tris[on].tolist()), strict=True))  # index triple -> the triangle's vertices
    return cost, face


def _placed(book: Selection, faces: list[tuple[int, int, int]], folds: bool) -> list[tuple[int, int, int]] | None:
    """``faces`` added to ``book`` one by one, each checked against it (only its edges with ``folds``): each fits
    the selection alone, together they may still overlap.  The faces, or None (``book`` unchanged) where one
    does not fit."""
    added = []
    for t in faces:
        if not (_edges_free(book, t) if folds else book.fits(*t)):
            for u in added:
                book.remove(*u)
            return None
        book.add(*t)
        added.append(t)
    return added


def _edges_free(book: Selection, face) -> bool:
    """Whether each edge of ``face`` is in at most one selected face (adding it keeps the surface
    edge-manifold).  A loop that passes a vertex twice can hold one edge twice: as a chord from one visit
    and as a chord or loop edge from the other."""
    a, b, c = face
    return all(len(book.third.get((x, y) if x < y else (y, x), ())) < 2 for x, y in ((a, b), (b, c), (a, c)))


def _close_loop(loop: list[int], book: Selection, support: SupportCache,
                limit: float) -> list[tuple[int, int, int]] | None:
    """Ear clipping, then (loops of 4 to ``WHOLE_LOOP_MAX`` edges) the best whole triangulation; a
    triangle's only triangulation is itself, which ear clipping has tried."""
    ears = _clip_loop(loop, book, support, limit)
    if ears is None and 4 <= len(loop) <= WHOLE_LOOP_MAX:
        ears = _best_triangulation(loop, book, support, limit)
    return ears


def _loop_edges(loop: list[int]) -> set[tuple[int, int]]:
    return {(a, b) if a < b else (b, a) for a, b in zip(loop, loop[1:] + loop[:1], strict=True)}


def _bridge(x: int, loops: list[list[int]], book: Selection, support: SupportCache,
            limit: float) -> tuple[int, int, int] | None:
    """Join vertex ``x`` (in no face) to a hole: the best-supported triangle (a, x, b) over an edge (a, b)
    of one of ``loops`` that lies on the surface and fits is added to ``book``, and x goes between a and
    b in that loop.  Returns the triangle, or None (nothing changed)."""
    tris = [(a, x, b, k, i) for k, lp in enumerate(loops)
            for i, (a, b) in enumerate(zip(lp, lp[1:] + lp[:1], strict=True))]
    if not tris:
        return None
    d = support(np.array([t[:3] for t in tris], dtype=np.int64))
    for j in np.argsort(d, kind="stable"):
        a, _, b, k, i = tris[j]
        if d[j] > limit:
            break
        if book.fits(a, x, b):
            book.add(a, x, b)
            loops[k].insert(i + 1, x)
            return (a, x, b)
    return None


def _reclip(loop: list[int], kept: dict, book: Selection, support: SupportCache, limit: float,
            max_loop: int) -> bool:
    """Close a boundary ``loop`` no ear fits by clipping again without the faces along it.

    Up to ``REPAIR_RINGS`` rings of faces around the hole are taken out, one ring at a time, until
    the hole they leave closes.  A vertex left in no face is first joined to the hole's boundary
    (:func:`_bridge`); a closing is kept only if every vertex of the removed faces is in some face
    again (one that drops a vertex has cut across the base of a spike the ring held).
    Otherwise everything goes back.  ``kept`` (sorted face -> face) and ``book`` are updated in place.
    """
    edges = _loop_edges(loop)
    if any(len(book.third.get(e, ())) != 1 for e in edges):  # changed by an earlier repair
        return False
    removed: list[tuple[int, int, int]] = []
    opened = set(edges)
    for _ in range(REPAIR_RINGS):
        ring = [kept[key] for key in {tuple(sorted((a, b, *book.third[(a, b)]))) for a, b in edges
                                      if len(book.third.get((a, b), ())) == 1}]
        if not ring:
            break
        for t in ring:
            book.remove(*t)
            del kept[tuple(sorted(t))]
        removed += ring
        opened.update(tuple(sorted(e)) for a, b, c in ring for e in ((a, b), (b, c), (a, c)))
        loops = [x for x in _loops_through(book, opened) if _loop_edges(x) & opened]
        if not loops or sum(map(len, loops)) > max_loop + 2 * len(loop):
            break
        # A vertex whose faces all went (the tip of a spike, or of a shallow cone whose artist fan is no
        # restricted-Delaunay candidate) joins the hole's boundary first, or clipping would leave it out.
        isolated = sorted({x for t in removed for x in t if not book.sectors[x]})
        bridged = [list(x) for x in loops]  # the next ring grows from ``loops`` as they were
        done = [t for x in isolated if (t := _bridge(x, bridged, book, support, limit))]
        for x in bridged:
            ears = _close_loop(x, book, support, limit)
            if ears is None:
                break
            done.extend(ears)
        else:
            if all(book.sectors[x] for t in removed for x in t):  # the book holds kept + done
                kept.update((tuple(sorted(t)), t) for t in done)
                return True
        for t in done:
            book.remove(*t)
        edges = set().union(*map(_loop_edges, loops))
    for t in removed:
        book.add(*t)
        kept[tuple(sorted(t))] = t
    return False


def fill_holes(vertices: np.ndarray, faces: np.ndarray, book: Selection, points: np.ndarray, limit: float,
               tree: cKDTree | None = None, max_loop: int = 64) -> np.ndarray:
    """Close boundary loops that lie on the input surface by ear clipping (or whole triangulation).

    Each loop of at most ``max_loop`` edges is clipped ear by ear, best-supported ear first; an ear is
    allowed when it lies on the surface (support distance at most ``limit``), adds no edge that
    already exists, and fits the selection (:meth:`Selection.fits`).  Where the ears lead into a
    dead end, a loop of up to ``WHOLE_LOOP_MAX`` edges takes its best whole triangulation
    (:func:`_best_triangulation`) under the same rules.  A loop that neither closes is tried again
    without the faces along it (:func:`_reclip`): a wrong face beside a hole is what most often
    blocks its ears (it folds onto them, or holds the edge they need), so the faces bordering the
    loop are taken out and the larger hole they leave is closed instead; if that does not close
    either, the faces go back and the loop stays open (an open input stays open).

    Returns
    -------
    (F', 3) int64 faces: the selection, with at most the faces bordering re-clipped loops exchanged.
    """
    support = SupportCache(vertices, points, tree, bound=limit)  # the same faces are asked for many times
    kept = {tuple(sorted(t)): tuple(t) for t in np.asarray(faces, dtype=np.int64).reshape(-1, 3).tolist()}
    stuck = []
    for loop in boundary_loops(faces):
        if len(loop) > max_loop:
            continue
        ears = _close_loop(loop, book, support, limit)
        if ears is None:
            stuck.append(loop)
        else:
            kept.update((tuple(sorted(t)), t) for t in ears)
    for loop in stuck:
        _reclip(loop, kept, book, support, limit, max_loop)
    return np.asarray(list(kept.values()), dtype=np.int64).reshape(-1, 3)
