"""Vertex decoder: cached decoding equals uncached decoding; sampled sequences obey the grammar."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fastmesh.models.choice import KIND_BLOCK, KIND_EOS, KIND_OFFSET, filter_logits, token_kinds, token_probs
from fastmesh.models.encoder import EncoderConfig, farthest_point_sample
from fastmesh.models.evidence import GAIN, SPREAD_EDGES
from fastmesh.models.generate import SamplingConfig, generate, generate_uncached
from fastmesh.models.vertex import VertexConfig, VertexDecoder, grammar_mask, grammar_mask_rows
from fastmesh.tokenizer import vertex as vt
from fastmesh.tokenizer.grid import quantize, split_cells

torch.set_num_threads(1)


def _model(seed: int = 0, anchors: int = 0, evidence: bool = False, normals: bool = False) -> VertexDecoder:
    torch.manual_seed(seed)
    enc = EncoderConfig(n_points=64, n_latents=4, dim=32, depth=1, heads=2, n_freqs=4, anchors=anchors)
    m = VertexDecoder(VertexConfig(dim=32, depth=2, heads=2, encoder=enc, evidence=evidence,
                                   evidence_normals=normals)).eval()
    with torch.no_grad():  # spread the logits so greedy choices are not near-ties
        m.head.weight.normal_(0, 1.0)
        m.tok_emb.weight.normal_(0, 0.5)
        if evidence:  # as if trained: strong, varied biases per evidence level
            for t in (m.evidence.table, m.evidence.block_table, m.evidence.skip_table, m.evidence.eos_table,
                      m.evidence.corner_table):
                if t is not None:
                    t.weight.normal_(0, 3.0 / GAIN)
    return m


def _points(b: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    pts = torch.rand(b, 64, 3, generator=g) - 0.5
    return pts, torch.nn.functional.normalize(torch.randn(b, 64, 3, generator=g), dim=-1)


def _prefix(m: VertexDecoder, b: int, seed: int = 0) -> torch.Tensor:
    with torch.no_grad():
        return m.condition(*_points(b, seed))


def _trim(row: torch.Tensor) -> list[int]:
    row = row.tolist()
    return row[: row.index(vt.EOS) + 1] if vt.EOS in row else [t for t in row if t != vt.PAD]


@pytest.mark.parametrize("seed,anchors,evidence,normals",
                         [(0, 0, False, False), (1, 0, False, False), (0, 8, False, False), (2, 8, True, False),
                          (3, 8, True, True)])
def test_cached_equals_uncached_at_temperature_zero(seed, anchors, evidence, normals):
    m = _model(seed, anchors, evidence, normals)
    prefix = _prefix(m, 3, seed)
    ev = m.point_evidence(*_points(3, seed)) if evidence else None
    cached = generate(m, prefix, SamplingConfig(temperature=0, max_vertices=12), evidence=ev)
    uncached = generate_uncached(m, prefix, max_vertices=12, evidence=ev)
    assert len(cached) == 3
    for a, b in zip(cached, uncached, strict=True):
        assert a.tolist() == _trim(b)
    assert any(len(a) > 4 for a in cached)  # not trivially BOS EOS


def test_anchored_prefix_has_one_token_per_anchor_and_follows_the_points():
    m = _model(0, anchors=8)
    prefix = _prefix(m, 2)
    assert prefix.shape == (2, 8, 32)
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(1, 64, 3, generator=g) - 0.5
    nrm = torch.nn.functional.normalize(torch.randn(1, 64, 3, generator=g), dim=-1)
    with torch.no_grad():
        moved = m.condition(pts + 0.1, nrm)
        assert not torch.allclose(m.condition(pts, nrm), moved)


def test_evidence_bias_counts_points_around_each_candidate_cell():
    """The bias of an offset token depends only on the point counts around its cell; a block token on its
    block's count and the occupied blocks it would skip; EOS on the occupied blocks still ahead."""
    m = _model(0, evidence=True)
    pts = torch.tensor([[[0.01, 0.01, 0.01]] * 5 + [[-0.45, -0.45, -0.45]]])  # 5 points in one cell, 1 far away
    ev = m.point_evidence(pts)
    blk = int(split_cells(quantize(pts[0, 0]))[0])  # cell (65, 65, 65): block (4, 4, 4), offset (1, 1, 1)
    bias = ev.logit_bias(torch.tensor([[blk, -1]]))
    tab, btab = GAIN * m.evidence.table.weight[:, 0], GAIN * m.evidence.block_table.weight[:, 0]
    stab, etab = GAIN * m.evidence.skip_table.weight[:, 0], GAIN * m.evidence.eos_table.weight[:, 0]
    here = vt.OFFSET0 + 1 * 256 + 1 * 16 + 1
    far = vt.OFFSET0 + 15 * 256 + 15 * 16 + 15  # cell (79, 79, 79): no point within 8 cells
    # 5 points -> level floor(log2 6) = 2 at every scale (2, 4, 8 cells): index (2 * 6 + 2) * 6 + 2
    assert torch.isclose(bias[0, 0, here], tab[(2 * 6 + 2) * 6 + 2])
    assert torch.isclose(bias[0, 0, far], tab[0])
    assert bias[0, 1, vt.OFFSET0:].abs().max() == 0  # no block yet: no offset evidence
    # Occupied blocks: 0 (the far point) and blk.  In blk both are behind: nothing skipped, nothing remaining.
    b0, b1, bb = vt.BLOCK0, vt.BLOCK0 + 1, vt.BLOCK0 + blk
    assert torch.isclose(bias[0, 0, bb], btab[2] + stab[0]) and torch.isclose(bias[0, 0, b0], btab[1] + stab[0])
    assert torch.isclose(bias[0, 0, b1], btab[0] + stab[0]) and torch.isclose(bias[0, 0, vt.EOS], etab[0])
    # Before any block: going to blk or block 1 skips block 0 (level 1); two occupied blocks remain (level 1).
    assert torch.isclose(bias[0, 1, bb], btab[2] + stab[1]) and torch.isclose(bias[0, 1, b0], btab[1] + stab[0])
    assert torch.isclose(bias[0, 1, b1], btab[0] + stab[1]) and torch.isclose(bias[0, 1, vt.EOS], etab[1])
    assert bias[0, :, [vt.PAD, vt.BOS]].abs().max() == 0


def test_corner_evidence_reads_the_spread_of_the_normals():
    """With ``evidence_normals`` an offset token also gets corner_table[state at 2 cells, state at 4 cells]:
    0 without points, 1 where the normals agree (a plane, seen from either side), higher where they bend."""
    m = _model(0, evidence=True, normals=True)
    up, side = [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]
    # Cell (65, 65, 65): 4 points with normals up and down (a thin sheet: flat).  Cell (69, 65, 65), in
    # another 2-cube and 4-cube (4..7 along x) of the same block: 2 points up, 2 sideways (a crease).
    pts = torch.tensor([[[0.01, 0.01, 0.01]] * 4 + [[0.04, 0.01, 0.01]] * 4])
    nrm = torch.tensor([[up, [0.0, 0.0, -1.0], up, [0.0, 0.0, -1.0], up, up, side, side]])
    ev = m.point_evidence(pts, nrm)
    blk = 4 * 64 + 4 * 8 + 4
    bias = ev.logit_bias(torch.tensor([[blk]]))[0, 0]
    tab, ctab = GAIN * m.evidence.table.weight[:, 0], GAIN * m.evidence.corner_table.weight[:, 0]
    n_states = len(SPREAD_EDGES) + 2

    def offset(x, y, z):
        return vt.OFFSET0 + x * 256 + y * 16 + z

    count = (2 * 6 + 2) * 6 + 3  # 4 points in the 2- and 4-cubes (level 2), all 8 in the 8-cube (level 3)
    # spread of (up, up, side, side) = 1 - |(2, 0, 2)| / 4 = 0.29: the top level; of (up, -up, ...) = 0.
    flat, crease = 1, len(SPREAD_EDGES) + 1
    assert torch.isclose(bias[offset(1, 1, 1)], tab[count] + ctab[flat * n_states + flat])
    assert torch.isclose(bias[offset(5, 1, 1)], tab[count] + ctab[crease * n_states + crease])
    assert torch.isclose(bias[offset(15, 15, 15)], tab[0] + ctab[0])  # no points near: state 0 at both scales
    with pytest.raises(ValueError, match="normals"):
        m.point_evidence(pts)


@pytest.mark.parametrize("top_k,top_p", [(50, 0.95), (5, 1.0), (0, 0.9), (0, 1.0), (3, 0.5)])
def test_fast_sampling_distribution_equals_filtering_the_whole_vocabulary(top_k, top_p):
    g = torch.Generator().manual_seed(0)
    logits = torch.randn(3, vt.VOCAB_SIZE, generator=g) * 3
    logits[:, :100] = float("-inf")  # masked by the grammar
    cfg = SamplingConfig(temperature=0.7, top_k=top_k, top_p=top_p)
    probs, ids = token_probs(logits, cfg)
    fast = torch.zeros_like(logits).scatter_add_(-1, ids, probs)
    slow = filter_logits(logits / 0.7, top_k, top_p).softmax(-1)
    assert torch.allclose(fast, slow, atol=1e-6)


def test_farthest_point_sample_spreads_and_is_deterministic():
    g = torch.Generator().manual_seed(0)
    # two tight clusters far apart: the second sample must come from the other cluster
    a = torch.randn(1, 50, 3, generator=g) * 0.01
    pts = torch.cat([a, a + 1.0], dim=1)
    idx = farthest_point_sample(pts, 2)
    assert idx[0, 0] == 0 and idx[0, 1] >= 50
    many = farthest_point_sample(pts.expand(3, -1, -1), 10)
    assert many.shape == (3, 10) and len(set(many[0].tolist())) == 10
    assert torch.equal(many[0], many[2])


def test_sampled_sequences_decode_and_respect_max_vertices():
    m = _model(2)
    with torch.no_grad():  # EOS unlikely, so the vertex budget is what ends most sequences
        m.head.weight[vt.EOS].fill_(0)
    prefix = _prefix(m, 6, 3)
    for seed in range(3):
        seqs = generate(m, prefix, SamplingConfig(temperature=1.0, top_k=0, top_p=1.0, max_vertices=9, seed=seed))
        for s in seqs:
            s = s.numpy()
            assert s[0] == vt.BOS and s[-1] == vt.EOS
            cells = vt.decode(s, strict=True)  # raises on any grammar violation
            assert 1 <= len(cells) <= 9
            assert len(np.unique(cells, axis=0)) == len(cells)
            assert (vt.encode(cells) == s).all()  # canonical: re-encoding gives the same tokens
        assert max(int((s >= vt.OFFSET0).sum()) for s in seqs) == 9


def test_face_count_condition_adds_one_prefix_token_per_target():
    from fastmesh.models.vertex import COUNT_BUCKETS, count_bucket

    assert count_bucket(torch.tensor([0, -5, 16, 32, 4096, 10 ** 6, 23])).tolist() == [0, 0, 1, 5, COUNT_BUCKETS - 1,
                                                                                        COUNT_BUCKETS - 1, 3]
    torch.manual_seed(0)
    enc = EncoderConfig(n_points=64, n_latents=4, dim=32, depth=1, heads=2, n_freqs=4)
    m = VertexDecoder(VertexConfig(dim=32, depth=2, heads=2, encoder=enc, count_condition=True)).eval()
    with torch.no_grad():
        m.count_emb.weight.normal_(0, 1.0)
        m.head.weight.normal_(0, 1.0)
    pts, nrm = _points(2)
    with torch.no_grad():
        none = m.condition(pts, nrm)
        asked = m.condition(pts, nrm, torch.tensor([100, 2000]))
    assert none.shape == (2, 5, 32) and torch.equal(none[:, :4], asked[:, :4])
    assert not torch.allclose(asked[0, 4], asked[1, 4]) and torch.equal(none, m.condition(pts, nrm, torch.zeros(2)))
    cached = generate(m, asked, SamplingConfig(temperature=0, max_vertices=10))
    uncached = generate_uncached(m, asked, max_vertices=10)
    for a, b in zip(cached, uncached, strict=True):
        assert a.tolist() == _trim(b)
    # Training reads the target from the batch: the loss changes with it.
    tokens = torch.tensor([[vt.BOS, vt.BLOCK0 + 3, vt.OFFSET0 + 7, vt.EOS]])
    l1 = m.loss(tokens, points=pts[:1], normals=nrm[:1], target_faces=torch.tensor([100]))
    l2 = m.loss(tokens, points=pts[:1], normals=nrm[:1], target_faces=torch.tensor([3000]))
    assert not torch.isclose(l1, l2)


def test_grammar_mask_rows_equals_the_vectorised_mask():
    """The decode loop's row-by-row mask is :func:`grammar_mask` for every kind of state: after BOS, a block, an
    offset (first and last block and offset included), EOS and PAD, with and without the vertex budget spent."""
    rng = np.random.default_rng(0)
    states = [(vt.BOS, -1, -1), (vt.EOS, 5, 7), (vt.PAD, 5, 7)]
    for b in [0, vt.N_BLOCKS - 1, *rng.integers(0, vt.N_BLOCKS, 20).tolist()]:
        states.append((vt.BLOCK0 + b, b, -1))
        for o in [0, vt.N_OFFSETS - 1, *rng.integers(0, vt.N_OFFSETS, 5).tolist()]:
            states.append((vt.OFFSET0 + o, b, o))
    prev, block, offset = (list(x) for x in zip(*states, strict=True))
    for spent in (False, True):
        eos_only = [spent or bool(k % 3 == 0) for k in range(len(prev))]
        slow = grammar_mask(torch.tensor(prev), torch.tensor(block), torch.tensor(offset),
                            eos_only=torch.tensor(eos_only))
        fast = grammar_mask_rows(prev, block, offset, eos_only)
        assert fast.dtype == torch.bool and torch.equal(fast, slow)


def test_token_kinds():
    kinds = token_kinds(torch.device("cpu"))
    assert kinds.shape == (vt.VOCAB_SIZE,)
    assert (kinds[:vt.BLOCK0] == KIND_EOS).all() and (kinds[vt.BLOCK0:vt.OFFSET0] == KIND_BLOCK).all()
    assert (kinds[vt.OFFSET0:] == KIND_OFFSET).all()
