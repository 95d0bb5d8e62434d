"""Prediction filtering against synthetic predictors (noisy copies of a true adjacency)."""

from __future__ import annotations

import numpy as np
import pytest

from fastmesh.evaluation.metrics import edge_metrics
from fastmesh.faces.filtering import (
    FilterConfig,
    adjacency_bandwidth,
    band_mask,
    edges_from_logits,
    filter_predictions,
    neighbour_radius,
    predict_edges,
    rcm_order,
)
from fastmesh.faces.meshops import edges_from_faces


def _shuffled_grid(k: int, seed: int):
    """True edges of a triangulated k x k grid whose vertex ids are shuffled (large bandwidth)."""
    idx = np.arange(k * k).reshape(k, k)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    f = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    perm = np.random.default_rng(seed).permutation(k * k)
    return edges_from_faces(perm[f]), k * k


def _noisy_logits(edges, n, seed, n_far=60, far_logit=(0.5, 1.2)):
    """True edges ~ +4, others ~ -4, plus ``n_far`` random pairs at moderately confident logits."""
    rng = np.random.default_rng(seed)
    lg = rng.normal(-4.0, 1.0, (n, n)).astype(np.float32)
    lg[edges[:, 0], edges[:, 1]] = rng.normal(4.0, 0.7, len(edges))
    a, b = np.sort(rng.integers(0, n, (n_far, 2)), axis=1).T
    far = a != b
    lg[a[far], b[far]] = rng.uniform(*far_logit, far.sum())
    lg = np.triu(lg, 1)
    return lg + lg.T


def _predictor(logits, log=None):
    def predict(order, mask):
        if log is not None:
            log.append((order.copy(), None if mask is None else mask.copy()))
        return logits[np.ix_(order, order)]

    return predict


def test_config_schedule():
    assert np.array_equal(FilterConfig().schedule(), np.full(5, 0.5))  # what ships: the 0.5 rule at every pass
    cfg = FilterConfig(first_threshold=0.8)
    t = cfg.schedule()
    assert len(t) == cfg.n_passes == 5 and t[0] == pytest.approx(0.8) and t[-1] == pytest.approx(0.5)
    assert np.all(np.diff(t) <= 0)
    assert FilterConfig(thresholds=(0.9, 0.5, 0.5, 0.5, 0.5)).schedule()[0] == 0.9
    with pytest.raises(ValueError):
        FilterConfig(thresholds=(0.9, 0.5)).schedule()
    with pytest.raises(ValueError):
        FilterConfig(first_threshold=1.0).schedule()


def test_helpers():
    m = band_mask(5, 1)
    assert m.sum() == 5 + 2 * 4 and m[0, 1] and not m[0, 2]
    r = np.array([0, 3, 0, 0, 0])
    assert band_mask(5, r)[1].tolist() == [True, True, True, True, True] and band_mask(5, r)[0].sum() == 1
    e = np.array([[0, 4], [1, 2], [2, 3]])
    assert adjacency_bandwidth(e) == 4 and adjacency_bandwidth(np.zeros((0, 2), int)) == 0
    assert neighbour_radius(e, 6, 2).tolist() == [4, 2, 2, 2, 4, 2]
    lg = np.full((3, 3), -5.0)
    lg[0, 1], lg[1, 0] = 3.0, -1.0  # symmetrised: mean logit 1.0 -> p = 0.73
    assert edges_from_logits(lg, 0.5).tolist() == [[0, 1]]
    assert edges_from_logits(lg, 0.8).tolist() == []


def test_rcm_shrinks_bandwidth():
    edges, n = _shuffled_grid(20, 0)
    order = rcm_order(edges, n)
    assert sorted(order.tolist()) == list(range(n))
    pos = np.empty(n, dtype=int)
    pos[order] = np.arange(n)
    assert adjacency_bandwidth(pos[edges]) < adjacency_bandwidth(edges) / 5


@pytest.mark.parametrize("seed", range(3))
def test_filtering_removes_far_false_positives(seed):
    edges, n = _shuffled_grid(18, seed)
    lg = _noisy_logits(edges, n, seed)
    plain = edge_metrics(edges_from_logits(lg, 0.5), edges)
    assert plain["fp"] >= 40  # the unfiltered 0.5 rule keeps the stray pairs
    # A strict first pass (0.8) fixes the masks from confident edges only; the later passes admit 0.5 inside them.
    res = filter_predictions(_predictor(lg), n, FilterConfig(first_threshold=0.8))
    m = edge_metrics(res.edges, edges)
    assert m["recall"] == 1.0  # every true edge kept, reported in the original indexing
    assert m["fp"] <= plain["fp"] // 5
    assert m["precision"] > 0.99
    assert [h["kind"] for h in res.history] == ["full", "bandwidth", "bandwidth", "candidate", "candidate"]


def test_predictor_sees_reordered_masks():
    edges, n = _shuffled_grid(10, 4)
    lg = _noisy_logits(edges, n, 4, n_far=10)
    calls = []
    res = filter_predictions(_predictor(lg, calls), n, FilterConfig(bandwidth_passes=1, candidate_passes=3))
    assert len(calls) == 5
    assert calls[0][1] is None and np.array_equal(calls[0][0], np.arange(n))
    for order, mask in calls[1:]:
        assert np.array_equal(order, res.order)
        assert mask.shape == (n, n) and mask.dtype == bool and mask.diagonal().all()
    # Every final edge is allowed by the last mask (in reordered positions).
    pos = np.empty(n, dtype=int)
    pos[res.order] = np.arange(n)
    last = calls[-1][1]
    assert last[pos[res.edges[:, 0]], pos[res.edges[:, 1]]].all()
    assert res.history[-1]["allowed"] == int(last.sum()) < res.history[1]["allowed"]


def test_no_reorder_and_plain_threshold():
    edges, n = _shuffled_grid(8, 5)
    lg = _noisy_logits(edges, n, 5, n_far=0)
    res = filter_predictions(_predictor(lg), n, FilterConfig(reorder=False, first_threshold=0.5))
    assert np.array_equal(res.order, np.arange(n))
    assert edge_metrics(res.edges, edges)["f1"] == 1.0


def test_bad_predictor_shape():
    with pytest.raises(ValueError):
        filter_predictions(lambda order, mask: np.zeros((3, 3)), 4)


def test_predict_edges_is_filtering_or_one_pass_at_the_final_threshold():
    edges, n = _shuffled_grid(6, 3)
    lg = _noisy_logits(edges, n, 4)
    cfg = FilterConfig(final_threshold=0.7)
    calls = []
    got, first = predict_edges(_predictor(lg, calls), n, cfg)
    np.testing.assert_array_equal(got, filter_predictions(_predictor(lg), n, cfg).edges)
    np.testing.assert_array_equal(first, lg)  # the unmasked first pass, in the input order
    assert len(calls) == cfg.n_passes and calls[0][1] is None
    calls.clear()
    got, first = predict_edges(_predictor(lg, calls), n, cfg, filtering=False)
    np.testing.assert_array_equal(got, edges_from_logits(lg, 0.7))
    np.testing.assert_array_equal(first, lg)
    assert len(calls) == 1
