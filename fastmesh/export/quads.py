"""Quad-dominant topology from a triangle mesh: pairs of triangles that share an edge become one quad where
together they are near-planar and well shaped.

Each interior edge between two consistently oriented triangles is a candidate; its quad's score is its shape
(how near its four corners are to right angles) lowered by how far it bends along the removed diagonal.  The
candidates are taken greedily, best first, each triangle joining at most one quad: a maximum-weight matching
would find a few more, but the greedy one keeps the best-shaped quads, which is what a modeller looks at.

With the face model's edge probabilities (:class:`EdgeEvidence`), the model's flat 4-cliques go first: the
candidates whose four sides the model predicted and whose removed diagonal it did not (an artist's quad, whose
diagonal was never an edge: the triangulation only added it).  Geometry alone cannot tell that quad from the
one its neighbour would make; the model was trained on the artist's edges and can.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..faces.surface_triangles import edge_log_prob

# A result vertex is the face stage's vertex at the same position to this share of the vertices' extent: the
# steps between them copy positions (or move a vertex away, which then has no evidence).
MATCH_TOL = 1e-9


@dataclass(frozen=True)
class QuadConfig:
    """When two triangles make a quad.

    ``max_bend``: largest angle between the two triangles' normals, degrees (near-planar).  ``min_angle`` and
    ``max_angle``: the range every corner of the quad must lie in, degrees (convex and not a sliver).
    ``min_score``: the lowest score a quad is kept at (1 is a flat square).
    ``side_prob`` and ``diagonal_prob``: with :class:`EdgeEvidence`, a quad is one of the model's flat 4-cliques
    where each of its four sides has at least probability ``side_prob`` and its removed diagonal less than
    ``diagonal_prob`` (the face stage's cut between an edge and none is 0.5).
    """

    max_bend: float = 30.0
    min_angle: float = 35.0
    max_angle: float = 150.0
    min_score: float = 0.25
    side_prob: float = 0.5
    diagonal_prob: float = 0.5


def _matched(points: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """(V,) int64 index of the row of ``points`` (N, 3) at each of ``vertices`` (V, 3), -1 where none is (to
    ``MATCH_TOL`` of the points' extent)."""
    vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    if len(points) == 0:
        return np.full(len(vertices), -1, np.int64)
    extent = float(np.ptp(points, axis=0).max()) or 1.0
    dist, idx = cKDTree(points).query(vertices)
    return np.where(dist <= MATCH_TOL * extent, idx, -1).astype(np.int64)


def _keys(pairs: np.ndarray, n: int) -> np.ndarray:
    """(E,) int64 one key per unordered pair of (E, 2) indices below ``n``."""
    return np.min(pairs, axis=1) * n + np.max(pairs, axis=1)


@dataclass(frozen=True)
class EdgeEvidence:
    """The face model's probabilities of the face stage's edges, kept by the vertices' positions: between the
    face stage and the written result the mesh is re-indexed (unused vertices dropped, pieces split, coinciding
    vertices welded), but a vertex keeps its position.

    Attributes
    ----------
    points : (N, 3) float64, the face stage's vertices
    keys : (K,) int64, sorted: the edges among them the model has a probability for (``i * N + j``, i < j)
    prob : (K,) float64, their probabilities
    """

    points: np.ndarray
    keys: np.ndarray
    prob: np.ndarray

    @classmethod
    def of_mesh(cls, vertices: np.ndarray, faces: np.ndarray, positions: np.ndarray, logits: np.ndarray,
                predicted: np.ndarray) -> EdgeEvidence:
        """The evidence about the edges of the face stage's mesh, as
        :func:`fastmesh.faces.surface_triangles.edge_log_prob` weighs it (a predicted edge at least 0.5).

        Parameters
        ----------
        vertices : (M, 3) float, faces : (F, 3) int
            The face stage's mesh: some of the model's vertices, and any it added (which have no evidence).
        positions : (N, 3) float, the vertices the model connected
        logits : (N, N) float, its edge logits among them (the first, unmasked pass)
        predicted : (E, 2) int, the edges it finally predicted (after filtering)
        """
        points = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
        f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
        edges = np.unique(np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1), axis=0)
        idx = _matched(np.asarray(positions, dtype=np.float64), points)[edges]
        known = np.all(idx >= 0, axis=1)
        prob = np.exp(edge_log_prob(idx[known], logits, predicted)) if known.any() else np.zeros(0)
        keys = _keys(edges[known], len(points))  # edges are sorted rows: their keys are sorted
        return cls(points, keys, prob)

    def moved(self, points: np.ndarray) -> EdgeEvidence:
        """The same evidence at the vertices' new positions ``points`` (N, 3), such as the input's frame."""
        return EdgeEvidence(np.asarray(points, dtype=np.float64), self.keys, self.prob)

    def probabilities(self, vertices: np.ndarray, pairs: np.ndarray) -> np.ndarray:
        """(E,) probability the model gave each pair of ``vertices`` (V, 3) that ``pairs`` (E, 2) name; NaN where
        it gave none (a vertex made or moved after the face stage, or two that were no edge of its mesh)."""
        pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        out = np.full(len(pairs), np.nan)
        if len(pairs) == 0 or len(self.keys) == 0:
            return out
        idx = _matched(self.points, vertices)[pairs]
        known = np.flatnonzero(np.all(idx >= 0, axis=1))
        keys = _keys(idx[known], len(self.points))
        at = np.minimum(np.searchsorted(self.keys, keys), len(self.keys) - 1)
        hit = self.keys[at] == keys
        out[known[hit]] = self.prob[at[hit]]
        return out


def flat_cliques(vertices: np.ndarray, quads: np.ndarray, evidence: EdgeEvidence, config: QuadConfig
                 ) -> np.ndarray:
    """(P,) bool: the candidate quads that are the model's flat 4-cliques (``config.side_prob`` and
    ``config.diagonal_prob``); a side or diagonal the evidence does not know never makes one.

    Parameters
    ----------
    vertices : (V, 3) float
    quads : (P, 4) int, corners in order as :func:`quad_corners` gives them: the removed diagonal is 0-2
    evidence : EdgeEvidence
    config : QuadConfig
    """
    q = np.asarray(quads, dtype=np.int64).reshape(-1, 4)
    sides = np.stack([q, np.roll(q, -1, axis=1)], axis=2).reshape(-1, 2)  # (4 P, 2): corner k -> k + 1
    prob = evidence.probabilities(vertices, np.concatenate([sides, q[:, [0, 2]]]))
    side, diagonal = prob[:len(sides)].reshape(-1, 4), prob[len(sides):]
    # NaN compares False: an unknown side is not predicted, an unknown diagonal not known to be absent.
    return np.all(side >= config.side_prob, axis=1) & (diagonal < config.diagonal_prob)


def interior_pairs(faces: np.ndarray) -> np.ndarray:
    """(P, 4) int64 rows ``(f, g, i, j)``: triangles ``f`` and ``g`` share the edge that runs from corner ``i`` to
    corner ``i + 1`` of ``f`` and the other way round from corner ``j`` to ``j + 1`` of ``g``; only edges in
    exactly two faces, consistently oriented.

    Parameters
    ----------
    faces : (F, 3) int
    """
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    n = len(faces)
    if n == 0:
        return np.zeros((0, 4), np.int64)
    a = faces.reshape(-1)  # corner k of face f at 3 f + k; the edge from it runs to the next corner
    b = faces[:, [1, 2, 0]].reshape(-1)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    order = np.lexsort((hi, lo))
    key = np.stack([lo[order], hi[order]], axis=1)
    same = np.all(key[1:] == key[:-1], axis=1)
    run_start = np.concatenate([[True], ~same])
    run_id = np.cumsum(run_start) - 1
    run_len = np.bincount(run_id)
    first = np.flatnonzero(same & (run_len[run_id[:-1]] == 2))  # the first of an edge's two half-edges
    h1, h2 = order[first], order[first + 1]
    opposite = a[h1] == b[h2]  # the two faces walk the edge in opposite directions: consistently oriented
    h1, h2 = h1[opposite], h2[opposite]
    return np.stack([h1 // 3, h2 // 3, h1 % 3, h2 % 3], axis=1)


def quad_corners(faces: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """(P, 4) int64 corners, in the faces' winding, of the quads that :func:`interior_pairs` rows make.

    Face ``f`` = (p, q, r) with the shared edge p -> q and face ``g`` with q -> p and opposite corner s give the
    quad (p, s, q, r): the diagonal p-q is removed.
    """
    f, g, i, j = (pairs[:, k] for k in range(4))
    faces = np.asarray(faces, dtype=np.int64)
    p, q, r = faces[f, i], faces[f, (i + 1) % 3], faces[f, (i + 2) % 3]
    s = faces[g, (j + 2) % 3]
    return np.stack([p, s, q, r], axis=1)


def _unit(x: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(x, axis=-1, keepdims=True)
    return x / np.where(n > 0, n, 1.0)


def quad_scores(vertices: np.ndarray, quads: np.ndarray, normals_f: np.ndarray, normals_g: np.ndarray,
                config: QuadConfig) -> np.ndarray:
    """(P,) score of each candidate quad, -inf where it fails ``config``'s limits.

    Parameters
    ----------
    vertices : (V, 3) float
    quads : (P, 4) int, corners in order
    normals_f, normals_g : (P, 3) float, unit normals of the two triangles
    """
    c = np.asarray(vertices, dtype=np.float64)[quads]  # (P, 4, 3)
    into = _unit(np.roll(c, -1, axis=1) - c)  # corner k -> k + 1
    back = _unit(np.roll(c, 1, axis=1) - c)   # corner k -> k - 1
    angles = np.degrees(np.arccos(np.clip(np.sum(into * back, axis=2), -1.0, 1.0)))  # (P, 4)
    bend = np.degrees(np.arccos(np.clip(np.sum(normals_f * normals_g, axis=1), -1.0, 1.0)))
    # Convex: the normals of the triangles across the other diagonal agree with the quad's own.
    n1 = np.cross(c[:, 1] - c[:, 0], c[:, 3] - c[:, 0])
    n2 = np.cross(c[:, 3] - c[:, 2], c[:, 1] - c[:, 2])
    mean = normals_f + normals_g
    convex = (np.sum(n1 * mean, axis=1) > 0) & (np.sum(n2 * mean, axis=1) > 0)
    shape = 1.0 - np.max(np.abs(angles - 90.0), axis=1) / 90.0
    score = shape * (1.0 - 0.5 * bend / config.max_bend)
    ok = (convex & (bend <= config.max_bend) & (angles.min(axis=1) >= config.min_angle)
          & (angles.max(axis=1) <= config.max_angle) & (score >= config.min_score))
    return np.where(ok, score, -np.inf)


def pair_triangles(vertices: np.ndarray, faces: np.ndarray, config: QuadConfig | None = None,
                   evidence: EdgeEvidence | None = None) -> np.ndarray:
    """Triangles merged into quads, greedily: (Q, 4) int64 rows ``(f, g, i, j)`` as :func:`interior_pairs`
    gives them, no triangle in two rows.  The model's flat 4-cliques (:func:`flat_cliques`, with ``evidence``)
    first, then the other quads, each group best score first; every quad passes ``config``'s shape limits.

    Parameters
    ----------
    vertices : (V, 3) float
    faces : (F, 3) int
    config : QuadConfig, optional
    evidence : EdgeEvidence, optional
        The face model's edge probabilities; without them the quads are chosen by shape alone.
    """
    config = config or QuadConfig()
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    cand = interior_pairs(faces)
    if len(cand) == 0:
        return cand
    v = np.asarray(vertices, dtype=np.float64)
    tri = v[faces]
    normals = _unit(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]))
    score = quad_scores(v, quad_corners(faces, cand), normals[cand[:, 0]], normals[cand[:, 1]], config)
    keep = np.isfinite(score)
    cand, score = cand[keep], score[keep]
    clique = (flat_cliques(v, quad_corners(faces, cand), evidence, config) if evidence is not None
              else np.zeros(len(cand), dtype=bool))
    used = np.zeros(len(faces), dtype=bool)
    chosen = []
    for k in np.lexsort((-score, ~clique)):  # cliques first, each by score; a loop over candidates: ~1 s/million
        f, g = cand[k, 0], cand[k, 1]
        if not (used[f] or used[g]):
            used[f] = used[g] = True
            chosen.append(k)
    return cand[np.asarray(chosen, dtype=np.int64)]


def quad_share(n_quads: int, n_triangles: int) -> float:
    """The quads' share of the polygons (quads and the triangles left), 0 for none."""
    total = n_quads + n_triangles
    return round(n_quads / total, 4) if total else 0.0
