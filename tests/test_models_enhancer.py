"""Fidelity enhancer: bounded residuals, refine() frame, padding, learning on one mesh."""

from __future__ import annotations

import numpy as np
import torch

from fastmesh.models.encoder import EncoderConfig
from fastmesh.models.enhancer import Enhancer, EnhancerConfig
from fastmesh.tokenizer import dequantize
from fastmesh.tokenizer.grid import CELL, LEVELS

torch.set_num_threads(1)


def _model(seed: int = 0) -> Enhancer:
    torch.manual_seed(seed)
    enc = EncoderConfig(n_points=64, n_latents=4, dim=32, depth=1, heads=2, n_freqs=4)
    return Enhancer(EnhancerConfig(dim=32, depth=2, heads=2, n_freqs=4, encoder=enc)).eval()


def _shape(n: int = 30, seed: int = 0):
    rng = np.random.default_rng(seed)
    q = np.unique(rng.integers(0, LEVELS, (2 * n, 3)), axis=0)[:n]
    pts = rng.uniform(-0.5, 0.5, (64, 3)).astype(np.float32)
    nrm = rng.normal(size=(64, 3)).astype(np.float32)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    return q, pts, nrm


def _t(q, pts, nrm):
    return torch.from_numpy(q)[None], torch.from_numpy(pts)[None], torch.from_numpy(nrm)[None]


def test_output_is_bounded_even_with_huge_weights():
    m = _model()
    with torch.no_grad():
        m.head.weight.mul_(1e4)
        out = m(*_t(*_shape()))
    assert out.shape == (1, 30, 3)
    assert out.abs().max() <= 0.5
    assert out.abs().max() > 0.45  # saturated, not just small


def test_refine_stays_inside_each_cell():
    m = _model()
    q, pts, nrm = _shape()
    with torch.no_grad():
        m.head.weight.mul_(1e3)
    v = m.refine(q, pts, nrm)
    assert v.shape == (30, 3) and v.dtype == np.float64
    assert np.abs(v - dequantize(q)).max() <= 0.5 * CELL + 1e-12
    assert np.abs(v - dequantize(q)).max() > 0.1 * CELL
    assert m.refine(np.zeros((0, 3), dtype=np.int64), pts, nrm).shape == (0, 3)


def test_padding_is_invisible():
    m = _model()
    q, pts, nrm = _shape(12)
    qp = np.concatenate([q, np.full((5, 3), 9)])
    with torch.no_grad():
        a = m(*_t(q, pts, nrm))
        b = m(*_t(qp, pts, nrm), valid=torch.tensor([[True] * 12 + [False] * 5]))
    torch.testing.assert_close(a[0], b[0, :12], rtol=1e-4, atol=1e-5)


def test_l1_ignores_padding():
    pred = torch.tensor([[[0.1, 0.2, 0.3], [0.5, 0.5, 0.5]]])
    target = torch.zeros(1, 2, 3)
    assert Enhancer.l1(pred, target, torch.tensor([[True, False]])).item() == np.float32(0.2)


def test_a_few_steps_reduce_the_loss_on_one_mesh():
    q, pts, nrm = _shape(40, seed=2)
    rng = np.random.default_rng(5)
    target = torch.from_numpy(rng.uniform(-0.4, 0.4, (1, 40, 3)).astype(np.float32))
    valid = torch.ones(1, 40, dtype=torch.bool)
    m = _model().train()
    opt = torch.optim.Adam(m.parameters(), lr=3e-3)
    losses = []
    for _ in range(60):
        loss = Enhancer.l1(m(*_t(q, pts, nrm), valid), target, valid)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.6 * losses[0]
