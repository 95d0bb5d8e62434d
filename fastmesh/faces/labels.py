"""The solid face stage's labels made a surface: the interface between inside and outside cells
(:func:`interface`), and the labels changed where the inside touches itself along an edge or at a vertex only
(:func:`made_manifold`), so that every edge has two triangles and every vertex one fan."""

from __future__ import annotations

import numpy as np

from .meshops import corner_fans, crowded_edges

# Rounds of filling or emptying the cells around non-manifold edges and vertices, the first CHOOSING_ROUNDS the
# cheaper of the two, the rest emptying: filling spreads (a filled cell touches others at an edge), and on a part
# one cell thick it spread to the whole hull; emptying can only take the inside away.
MANIFOLD_ROUNDS = 16
CHOOSING_ROUNDS = 8


def interface(tri: np.ndarray, a: np.ndarray, b: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """(F, 3) the triangles between an inside and an outside cell, wound from the inside one to the outside one
    (``tri`` wound outward of ``a``, as :func:`fastmesh.faces.solid.cell_faces` gives them)."""
    ins_a = inside[a]
    ins_b = np.where(b < 0, False, inside[np.maximum(b, 0)])
    out = tri[ins_a & ~ins_b]
    return np.concatenate([out, tri[~ins_a & ins_b][:, [0, 2, 1]]])


def made_manifold(tets: np.ndarray, neighbours: np.ndarray, tri: np.ndarray, a: np.ndarray, b: np.ndarray,
                  inside: np.ndarray, inside_cost: np.ndarray, outside_cost: np.ndarray, n_vertices: int
                  ) -> np.ndarray:
    """``inside`` (K,) bool made a manifold's inside, in up to ``MANIFOLD_ROUNDS`` rounds.

    Around an edge in more than two interface triangles, or a vertex of several fans, the inside cells of its
    star fall into several groups joined through triangles, or the outside ones do (the inside touches itself
    along an edge or at the vertex only).  All groups but the dearest of one kind change label: the inside ones
    emptied or the outside ones filled, whichever the data term (``inside_cost``, ``outside_cost`` (K,)) charges
    less for (only emptied after ``CHOOSING_ROUNDS``, which ends: choices can undo each other's).
    """
    inside = inside.copy()
    for round_ in range(MANIFOLD_ROUNDS):
        f = interface(tri, a, b, inside)
        if not len(f):
            break
        simplices = [[int(u), int(w)] for u, w in crowded_edges(f)]
        simplices += [[int(u)] for u in np.flatnonzero(_pinched_vertices(f, n_vertices))]
        if not simplices:
            break
        for simplex in simplices:
            star = np.flatnonzero(np.isin(tets, simplex).sum(1) == len(simplex))
            _star_made_one(simplex, star, tets, neighbours, inside, inside_cost, outside_cost,
                           round_ < CHOOSING_ROUNDS)
    return inside


def _star_made_one(simplex: list[int], star: np.ndarray, tets: np.ndarray, neighbours: np.ndarray, inside: np.ndarray,
                   inside_cost: np.ndarray, outside_cost: np.ndarray, choose: bool) -> None:
    """Relabel, in place, the cells of the ``star`` (S,) of ``simplex`` (a vertex or an edge) so that its inside
    cells form one group joined through triangles around it and its outside ones (the outside cell among them)
    another: see :func:`made_manifold`."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    local = {int(t): i for i, t in enumerate(star)}
    n = len(star)  # node n: the outside cell
    rows, cols = [], []
    for i, t in enumerate(star):
        for j in range(4):
            if tets[t, j] in simplex:
                continue  # the triangle opposite a corner of the simplex leaves its star
            m = int(neighbours[t, j])
            other = n if m < 0 else local.get(m)
            if other is not None and (inside[t] == (m >= 0 and inside[m])):
                rows.append(i)
                cols.append(other)
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n + 1, n + 1))
    label = connected_components(graph, directed=False)[1]
    ins = np.r_[inside[star], False]
    cost = np.r_[np.where(inside[star], outside_cost[star], inside_cost[star]), np.inf]  # to change label
    groups = {kind: [g for g in np.unique(label[ins == kind])] for kind in (True, False)}
    spend = {kind: cost_of_all_but_dearest(label, cost, gs) for kind, gs in groups.items()}
    kind = True if not choose else bool(spend[False] > spend[True])
    if len(groups[kind]) < 2:
        kind = not kind
        if len(groups[kind]) < 2 or (not kind and not choose):
            return
    dearest = max(groups[kind], key=lambda g: cost[label == g].sum())
    change = (ins == kind) & (label != dearest)
    inside[star[change[:n]]] = not kind


def cost_of_all_but_dearest(label: np.ndarray, cost: np.ndarray, groups: list) -> float:
    """The summed ``cost`` (S,) of the nodes in every one of ``groups`` (labels in ``label`` (S,)) but the dearest
    (inf: the group holds a node that cannot change)."""
    if len(groups) < 2:
        return np.inf
    sums = sorted(float(cost[label == g].sum()) for g in groups)
    return float(np.sum(sums[:-1]))


def _pinched_vertices(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """(N,) bool, the vertices whose faces form several fans."""
    corner = faces.T.reshape(-1)
    pairs = np.unique(np.c_[corner, corner_fans(faces)], axis=0)
    return np.bincount(pairs[:, 0], minlength=n_vertices) > 1
