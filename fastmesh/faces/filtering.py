"""Prediction filtering (METHOD.md, "Post-processing"): re-predict the adjacency under locality masks.

Edges of an artist mesh join vertices that are close in a bandwidth-reducing order, so a
confident first adjacency tells where each vertex's true neighbours can be:

1. Pass 0 predicts with no mask; its edges above the first threshold give the graph.
2. Vertices are reordered breadth-first to shrink the bandwidth (reverse Cuthill-McKee).
3. Bandwidth passes: B = bandwidth of the current prediction in the new order; the model
   re-predicts with the mask ``|i - j| <= B`` (as an attention mask, and edges outside it
   are dropped).
4. Candidate passes: ``r_i = max(min_radius, farthest predicted neighbour of i)``; the
   mask ``|i - j| <= r_i`` (row i) re-predicts; an edge needs both of its rows to allow it.

Thresholds (probabilities) move from ``first_threshold`` to ``final_threshold`` over the
passes: the strict early passes fix the masks from confident edges, the later ones admit
less confident edges only inside them, so far-away false positives fall out.

The model is a callable ``predict(order, mask) -> logits``: ``order`` (N,) is a permutation
(position k holds vertex ``order[k]``), ``mask`` an (N, N) bool array in that order (True =
allowed; the diagonal is always True) or None, and the logits come back in that order.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

Predictor = Callable[[np.ndarray, "np.ndarray | None"], np.ndarray]


@dataclass
class FilterConfig:
    """Parameters of :func:`filter_predictions`; the defaults are what ships (``weights/pipeline.json``).

    Attributes
    ----------
    bandwidth_passes, candidate_passes : int
        Re-predictions under the bandwidth mask, then under the candidate mask (paper: 2 and 2).
    first_threshold, final_threshold : float
        Edge probability thresholds of pass 0 and of the last pass; passes in between are
        spaced linearly.  Equal values give the plain 0.5 rule at every pass.
    thresholds : tuple of float, optional
        Explicit per-pass thresholds (1 + bandwidth_passes + candidate_passes of them).
    min_radius : int
        Smallest candidate radius r_i (paper: 2).
    bandwidth_quantile : float
        B is this quantile of |i - j| over predicted edges (1.0 = the bandwidth, as in the
        paper; lower values ignore a few stray long edges).
    reorder : bool
        Reverse Cuthill-McKee reordering after pass 0 (False keeps the input order).
    """

    bandwidth_passes: int = 2
    candidate_passes: int = 2
    first_threshold: float = 0.5
    final_threshold: float = 0.5
    thresholds: tuple[float, ...] | None = None
    min_radius: int = 2
    bandwidth_quantile: float = 1.0
    reorder: bool = True

    @property
    def n_passes(self) -> int:
        return 1 + self.bandwidth_passes + self.candidate_passes

    def schedule(self) -> np.ndarray:
        """(n_passes,) probability thresholds."""
        if self.thresholds is not None:
            t = np.asarray(self.thresholds, dtype=np.float64)
            if len(t) != self.n_passes:
                raise ValueError(f"need {self.n_passes} thresholds, got {len(t)}")
        else:
            t = np.linspace(self.first_threshold, self.final_threshold, self.n_passes)
        if not ((t > 0) & (t < 1)).all():
            raise ValueError("thresholds are probabilities in (0, 1)")
        return t


@dataclass
class FilterResult:
    """Outcome of :func:`filter_predictions`.

    Attributes
    ----------
    edges : (E, 2) int64
        Final edges (i < j) in the ORIGINAL vertex indexing.
    order : (N,) int64
        The reordering used (position k holds vertex ``order[k]``).
    history : list of dict
        Per pass: ``pass``, ``kind`` (full / bandwidth / candidate), ``threshold``, ``edges``
        and the mask size (``allowed`` pairs, None for the full pass), ``bandwidth``.
    """

    edges: np.ndarray
    order: np.ndarray
    history: list = field(default_factory=list)


def band_mask(n: int, radius) -> np.ndarray:
    """(n, n) bool: ``|i - j| <= radius`` (scalar) or ``<= radius[i]`` (per row)."""
    idx = np.arange(n, dtype=np.int32 if n < 2**31 else np.int64)
    d = np.abs(idx[None, :] - idx[:, None])
    r = np.asarray(radius)
    return d <= (r[:, None] if r.ndim else r)


def adjacency_bandwidth(edges: np.ndarray, quantile: float = 1.0) -> int:
    """Bandwidth max |i - j| (or its ``quantile``) of (E, 2) edges; 0 without edges."""
    if len(edges) == 0:
        return 0
    d = np.abs(edges[:, 0] - edges[:, 1])
    return int(d.max() if quantile >= 1 else np.ceil(np.quantile(d, quantile)))


def neighbour_radius(edges: np.ndarray, n: int, min_radius: int = 2) -> np.ndarray:
    """(n,) r_i = max(min_radius, max |i - j| over i's edges)."""
    r = np.full(n, min_radius, dtype=np.int64)
    if len(edges):
        d = np.abs(edges[:, 0] - edges[:, 1])
        np.maximum.at(r, edges[:, 0], d)
        np.maximum.at(r, edges[:, 1], d)
    return r


def rcm_order(edges: np.ndarray, n: int) -> np.ndarray:
    """Reverse Cuthill-McKee order (breadth-first, low degree first) of an (E, 2) graph."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import reverse_cuthill_mckee

    if len(edges) == 0:
        return np.arange(n)
    a = sp.coo_matrix((np.ones(2 * len(edges), dtype=np.int8),
                       (np.r_[edges[:, 0], edges[:, 1]], np.r_[edges[:, 1], edges[:, 0]])), shape=(n, n)).tocsr()
    return np.asarray(reverse_cuthill_mckee(a, symmetric_mode=True), dtype=np.int64)


def edges_from_logits(logits: np.ndarray, threshold: float, mask: np.ndarray | None = None) -> np.ndarray:
    """(N, N) logits -> (E, 2) edges (i < j) with symmetrised probability above ``threshold``.

    The logits are averaged with their transpose (the edge head need not be symmetric);
    with a mask, both (i, j) and (j, i) must be allowed.
    """
    lg = np.asarray(logits, dtype=np.float32)
    if lg.ndim != 2 or lg.shape[0] != lg.shape[1]:
        raise ValueError(f"logits must be N x N, got {lg.shape}")
    cut = np.log(threshold / (1 - threshold))
    on = (lg + lg.T) > 2 * cut
    if mask is not None:
        on &= mask & mask.T
    i, j = np.nonzero(np.triu(on, 1))
    return np.stack([i, j], axis=1).astype(np.int64)


def filter_predictions(predict: Predictor, n: int, config: FilterConfig | None = None) -> FilterResult:
    """Run the filtering passes against a face model.

    Parameters
    ----------
    predict : callable
        ``predict(order, mask) -> (N, N) logits`` (see module docstring).
    n : int
        Number of vertices.
    config : FilterConfig

    Returns
    -------
    FilterResult with the final edges in the original indexing.
    """
    cfg = config or FilterConfig()
    thr = cfg.schedule()
    order = np.arange(n, dtype=np.int64)
    edges = edges_from_logits(_call(predict, order, None, n), thr[0])
    history = [{"pass": 0, "kind": "full", "threshold": float(thr[0]), "edges": len(edges), "allowed": None,
                "bandwidth": adjacency_bandwidth(edges)}]
    if cfg.reorder and n > 1:
        new = rcm_order(edges, n)  # positions of the current order -> new positions
        pos = np.empty(n, dtype=np.int64)
        pos[new] = np.arange(n)
        order, edges = order[new], np.sort(pos[edges], axis=1)
    for p in range(1, cfg.n_passes):
        if p <= cfg.bandwidth_passes:
            kind, b = "bandwidth", adjacency_bandwidth(edges, cfg.bandwidth_quantile)
            mask = band_mask(n, max(b, cfg.min_radius))
        else:
            kind = "candidate"
            mask = band_mask(n, neighbour_radius(edges, n, cfg.min_radius))
        edges = edges_from_logits(_call(predict, order, mask, n), thr[p], mask)
        history.append({"pass": p, "kind": kind, "threshold": float(thr[p]), "edges": len(edges),
                        "allowed": int(mask.sum()), "bandwidth": adjacency_bandwidth(edges)})
    out = np.sort(order[edges], axis=1) if len(edges) else edges.reshape(0, 2)
    out = out[np.lexsort((out[:, 1], out[:, 0]))] if len(out) else out
    return FilterResult(edges=out, order=order, history=history)


def _call(predict: Predictor, order: np.ndarray, mask: np.ndarray | None, n: int) -> np.ndarray:
    logits = np.asarray(predict(order.copy(), mask))
    if logits.shape != (n, n):
        raise ValueError(f"predict returned shape {logits.shape}, expected {(n, n)}")
    return logits


def predict_edges(predict: Predictor, n: int, config: FilterConfig, filtering: bool = True
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The face stage's edges among ``n`` vertices, and the logits of its first pass.

    With ``filtering``: :func:`filter_predictions` (its first pass is the unmasked one).  Without: that
    one unmasked pass in the input order, which is then also the last: cut at ``config.final_threshold``.

    Returns
    -------
    edges : (E, 2) int64, i < j; logits : (n, n) float32 of the unmasked pass in the input order (used to
    score candidate triangles).
    """
    first: list[np.ndarray] = []

    def keep_first(order: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
        out = predict(order, mask)
        if not first:
            first.append(out)
        return out

    if filtering:
        edges = filter_predictions(keep_first, n, config).edges
    else:
        edges = edges_from_logits(keep_first(np.arange(n), None), config.final_threshold)
    return edges, first[0]
