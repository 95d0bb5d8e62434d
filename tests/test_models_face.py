"""Face model: edge head algebra, chunking, attention masks, equivariance, loss, training masks."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from fastmesh.faces.filtering import FilterConfig, band_mask
from fastmesh.faces.meshops import edges_from_faces
from fastmesh.models.encoder import EncoderConfig
from fastmesh.models.face import OUTSIDE, FaceModel, FaceModelConfig, asymmetric_loss, mask_spans
from fastmesh.tokenizer import quantize_mesh
from fastmesh.tokenizer.grid import LEVELS
from fastmesh.training.tasks import face_training_mask

torch.set_num_threads(1)


def tiny_config(**kw) -> FaceModelConfig:
    enc = EncoderConfig(n_points=64, n_latents=4, dim=32, depth=1, heads=2, n_freqs=4)
    base = dict(dim=32, depth=2, heads=2, edge_heads=4, edge_head_dim=6, edge_mlp_hidden=8, pair_chunk=7,
                n_freqs=4, encoder=enc)
    base.update(kw)
    return FaceModelConfig(**base)


def _shape(n: int = 20, seed: int = 0):
    rng = np.random.default_rng(seed)
    q = np.unique(rng.integers(0, LEVELS, (n * 2, 3)), axis=0)[:n]
    pts = rng.uniform(-0.5, 0.5, (64, 3)).astype(np.float32)
    nrm = rng.normal(size=(64, 3)).astype(np.float32)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    return q, pts, nrm


def _model(seed: int = 0, **kw) -> FaceModel:
    torch.manual_seed(seed)
    return FaceModel(tiny_config(**kw)).eval()


def _t(q, pts, nrm):
    return torch.from_numpy(q)[None], torch.from_numpy(pts)[None], torch.from_numpy(nrm)[None]


def _edge_head_inputs(pairs: bool, n: int = 23):
    """A tiny model (random pair weights when it reads pairs), and its edge head's vertex features and
    pair context for an n-vertex shape."""
    m = _model(pair_evidence=pairs)
    if pairs:
        torch.nn.init.normal_(m.pair_fc.weight)
    qt, pt, nt = _t(*_shape(n))
    with torch.no_grad():
        return m, m.backbone(qt, m.backbone.condition(pt, nt)), m.pair_context(qt, pt, nt)


@pytest.mark.parametrize("pairs", [False, True])
def test_chunked_edge_logits_equal_unchunked(pairs):
    m, h, ctx = _edge_head_inputs(pairs)
    with torch.no_grad():
        a = m.edge_logits(h, chunk=5, pairs=ctx)
        b = m.edge_logits(h, chunk=1000, pairs=ctx)
    assert a.shape == (1, 23, 23)
    torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)


def test_edge_head_is_the_spacetime_distance_mlp():
    """Logits equal MLP(||u1_i - u1_j||^2 - ||u2_i - u2_j||^2 per head), computed the slow way."""
    m = _model()
    h = torch.randn(1, 9, 32)
    with torch.no_grad():
        got = m.edge_logits(h)[0]
        u = m.edge_proj(h[0]).view(9, 4, 2, 3)
        u1, u2 = F.normalize(u[:, :, 0], dim=-1), F.normalize(u[:, :, 1], dim=-1)
        d = ((u1[:, None] - u1[None]) ** 2).sum(-1) - ((u2[:, None] - u2[None]) ** 2).sum(-1)  # (9, 9, H)
        want = m.edge_out(F.gelu(m.edge_fc(d)))[..., 0]
    torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(got, got.T)  # symmetric by construction


@pytest.mark.parametrize("bias", [False, True])
def test_attention_mask_blocks_attention(bias):
    m = _model(distance_bias=bias)
    q, pts, nrm = _shape(12)
    q2 = q.copy()
    q2[5] = (q2[5] + 17) % LEVELS  # move vertex 5
    mask = torch.ones(1, 12, 12, dtype=torch.bool)
    mask[0, 0] = False  # vertex 0 sees nobody but itself (and the prefix)
    with torch.no_grad():
        prefix = m.backbone.condition(*_t(q, pts, nrm)[1:])
        h_a = m.backbone(torch.from_numpy(q)[None], prefix, mask=mask)
        h_b = m.backbone(torch.from_numpy(q2)[None], prefix, mask=mask)
        h_c = m.backbone(torch.from_numpy(q)[None], prefix)
        h_d = m.backbone(torch.from_numpy(q2)[None], prefix)
    torch.testing.assert_close(h_a[0, 0], h_b[0, 0])  # blocked: vertex 5 cannot reach vertex 0
    assert not torch.allclose(h_a[0, 1], h_b[0, 1])  # vertex 1 still sees it
    assert not torch.allclose(h_c[0, 0], h_d[0, 0])  # without the mask it does


@pytest.mark.parametrize("bias", [False, True])
def test_padding_is_invisible(bias):
    m = _model(distance_bias=bias)
    q, pts, nrm = _shape(10)
    qp = np.concatenate([q, np.full((4, 3), 77)])
    valid = torch.tensor([[True] * 10 + [False] * 4])
    with torch.no_grad():
        a = m(*_t(q, pts, nrm))
        b = m(*_t(qp, pts, nrm), valid=valid)
    torch.testing.assert_close(a[0], b[0, :10, :10], rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize(("bias", "pairs"), [(False, False), (True, False), (False, True)])
def test_logits_are_permutation_equivariant(bias, pairs):
    m = _model(distance_bias=bias, pair_evidence=pairs)
    if pairs:
        torch.nn.init.normal_(m.pair_fc.weight)
    q, pts, nrm = _shape(15)
    perm = np.random.default_rng(3).permutation(15)
    with torch.no_grad():
        a = m(*_t(q, pts, nrm))[0]
        b = m(*_t(q[perm], pts, nrm))[0]
    p = torch.from_numpy(perm)
    torch.testing.assert_close(b, a[p][:, p], rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("pairs", [False, True])
def test_predictor_follows_order_and_mask(pairs):
    m = _model(pair_evidence=pairs)
    if pairs:
        torch.nn.init.normal_(m.pair_fc.weight)
    q, pts, nrm = _shape(14)
    predict = m.predictor(q, pts, nrm)
    order = np.random.default_rng(1).permutation(14)
    mask = np.abs(np.arange(14)[:, None] - np.arange(14)[None]) <= 3
    with torch.no_grad():
        want = m(torch.from_numpy(q[order])[None], *_t(q, pts, nrm)[1:], mask=torch.from_numpy(mask)[None])[0]
        full = m(*_t(q, pts, nrm))[0]
    got = predict(order, mask)
    assert got.shape == (14, 14) and got.dtype == np.float32
    np.testing.assert_allclose(got[mask], want.numpy()[mask], rtol=1e-4, atol=1e-5)  # only these are read
    np.testing.assert_allclose(predict(np.arange(14), None), full.numpy(), rtol=1e-4, atol=1e-5)
    assert not np.allclose(got[mask], full.numpy()[order][:, order][mask], atol=1e-4)  # the mask changed it


@pytest.mark.parametrize("pairs", [False, True])
def test_edge_logits_over_column_spans_equal_the_whole_computation(pairs):
    """The inference path: one triangle of the symmetric logits, and only each row chunk's span of columns."""
    m, h, ctx = _edge_head_inputs(pairs)
    radius = np.random.default_rng(2).integers(0, 6, 23)
    mask = band_mask(23, radius)
    mask = mask & mask.T
    mask[5] = mask[:, 5] = False  # a vertex with no allowed pair
    spans = mask_spans(mask)
    assert spans[5].tolist() == [0, 0] and spans[0, 0] == 0 and spans[22, 1] == 23
    with torch.no_grad():
        whole = m.edge_logits(h, chunk=4, pairs=ctx)[0]
        part = m.edge_logits(h, chunk=4, pairs=ctx, columns=spans)[0]
        every = m.edge_logits(h, chunk=4, pairs=ctx, columns=np.tile([0, 23], (23, 1)))[0]
    torch.testing.assert_close(every, whole, rtol=1e-5, atol=1e-5)
    assert torch.equal(every, every.T) and torch.equal(part, part.T)
    inside = torch.zeros(23, 23, dtype=torch.bool)
    for i, (a, b) in enumerate(spans):
        inside[i, a:b] = True
    torch.testing.assert_close(part[inside], whole[inside], rtol=1e-5, atol=1e-5)  # up to the rounding of matmuls
    assert (part[torch.from_numpy(~mask)] == OUTSIDE).any()  # columns no row of a chunk needs are skipped
    assert (torch.isclose(part, whole, rtol=1e-5, atol=1e-5) | (part == OUTSIDE)).all()


def test_predict_edges_with_and_without_filtering():
    m = _model()
    q, pts, nrm = _shape(16)
    with torch.no_grad():
        m.edge_out.bias.fill_(0.3)  # make some pairs edges
    plain = m.predict_edges(q, pts, nrm)
    filt = m.predict_edges(q, pts, nrm, FilterConfig(bandwidth_passes=1, candidate_passes=1))
    for e in (plain, filt):
        assert e.ndim == 2 and e.shape[1] == 2 and e.dtype == np.int64
        assert (e[:, 0] < e[:, 1]).all() and (e >= 0).all() and (e < 16).all()
    assert len(plain) > 0
    assert m.predict_edges(q[:1], pts, nrm).shape == (0, 2)


def test_asymmetric_loss_matches_hand_computation():
    logits = torch.tensor([2.0, -1.0, -4.0, 0.5, 0.3])
    target = torch.tensor([True, False, False, False, True])
    weight = torch.tensor([1.0, 1.0, 1.0, 1.0, 0.0])

    def sig(x):
        return 1 / (1 + math.exp(-x))

    pos = -math.log(sig(2.0))  # gamma+ = 0: plain log-likelihood
    neg1 = -((sig(-1.0) - 0.05) ** 3) * math.log(1 - (sig(-1.0) - 0.05))
    neg2 = 0.0  # p = 0.018 < clip: no loss at all
    neg3 = -((sig(0.5) - 0.05) ** 3) * math.log(1 - (sig(0.5) - 0.05))
    got = asymmetric_loss(logits, target, weight)
    assert got.item() == pytest.approx(pos + neg1 + neg2 + neg3, rel=1e-5)
    # gradients are finite even for confident negatives
    x = torch.tensor([30.0, -30.0], requires_grad=True)
    asymmetric_loss(x, torch.tensor([False, True])).backward()
    assert torch.isfinite(x.grad).all()


def _octahedron():
    v = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.float64) * 0.45
    f = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    # subdivide once so there are non-edges to learn
    import trimesh

    mesh = trimesh.Trimesh(v, f, process=False).subdivide()
    return quantize_mesh(np.asarray(mesh.vertices), np.asarray(mesh.faces))


def test_a_few_steps_reduce_the_loss_on_one_mesh():
    q, f, _ = _octahedron()
    edges = edges_from_faces(f)
    n = len(q)
    target = torch.zeros(1, n, n, dtype=torch.bool)
    target[0, edges[:, 0], edges[:, 1]] = True
    upper = torch.triu(torch.ones(1, n, n, dtype=torch.bool), 1)
    _, pts, nrm = _shape(4)
    m = _model(dim=48).train()
    opt = torch.optim.Adam(m.parameters(), lr=3e-3)
    losses = []
    for _ in range(40):
        loss = asymmetric_loss(m(*_t(q, pts, nrm)), target, upper) / len(edges)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0]


@pytest.mark.parametrize("kind", ["full", "negative", "bandwidth", "candidate"])
def test_training_masks_keep_every_true_edge(kind):
    q, f, _ = _octahedron()
    edges = edges_from_faces(f)
    n = len(q)
    order, attn, score = face_training_mask(edges, n, kind, np.random.default_rng(0))
    assert sorted(order) == list(range(n))
    pos = np.empty(n, dtype=np.int64)
    pos[order] = np.arange(n)
    e = np.sort(pos[edges], axis=1)
    assert score[e[:, 0], e[:, 1]].all()  # positives always scored (the masks come from true edges)
    assert not np.tril(score).any()  # pairs i < j only
    if kind in ("full", "negative"):
        assert attn is None
    else:
        assert attn.shape == (n, n) and attn[e[:, 0], e[:, 1]].all() and attn[e[:, 1], e[:, 0]].all()
        assert score.sum() < n * (n - 1) // 2  # the mask actually restricts
    if kind == "negative":
        assert score.sum() > len(edges)  # some negatives too
