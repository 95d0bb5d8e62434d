"""Candidates decoded as one batch: row k is exactly what seed + k gives decoded alone."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_cells import _cell_grids

from fastmesh.evaluation.primitives import point_cloud, primitive
from fastmesh.faces.support import weighed_fit
from fastmesh.models.cells import flat_index
from fastmesh.models.encoder import EncoderConfig
from fastmesh.models.evidence import GAIN
from fastmesh.models.generate import SamplingConfig, StackedEvidence, generate
from fastmesh.models.onnx_decode import NumpyCache, OrtDecoder
from fastmesh.models.vertex import VertexConfig, VertexDecoder
from fastmesh.params import GenerateParams
from fastmesh.pipeline import Pipeline
from fastmesh.shapes.io import input_surface
from fastmesh.shapes.shape import Normalization
from fastmesh.tokenizer import vertex as vt

torch.set_num_threads(1)
B = 4


def _model(seed: int = 0, cells: bool = False, counts: bool = False) -> VertexDecoder:
    torch.manual_seed(seed)
    enc = EncoderConfig(n_points=64, n_latents=4, dim=32, depth=1, heads=2, n_freqs=4, anchors=8)
    m = VertexDecoder(VertexConfig(dim=32, depth=2, heads=2, encoder=enc, evidence=True, evidence_normals=True,
                                   evidence_cells=cells, evidence_counts=counts))
    with torch.no_grad():  # spread the logits and make the evidence matter, as if trained
        m.head.weight.normal_(0, 1.0)
        m.tok_emb.weight.normal_(0, 0.5)
        tables = (m.evidence.cell_block_table, m.evidence.cell_skip_table, m.evidence.cell_eos_table) if cells else (
            m.evidence.table, m.evidence.block_table, m.evidence.skip_table, m.evidence.eos_table,
            m.evidence.corner_table)
        if counts:
            tables += (m.evidence.stay_table, m.evidence.rest_table, m.evidence.count_table)
        for t in tables:
            t.weight.normal_(0, 3.0 / GAIN)
    return m.eval()


def _inputs(m: VertexDecoder, seed: int = 0):
    """B different shapes' prefixes and evidences (with their own cell log-odds if the decoder reads them),
    each computed alone."""
    g = torch.Generator().manual_seed(seed)
    pts = torch.rand(B, 64, 3, generator=g) - 0.5
    nrm = torch.nn.functional.normalize(torch.randn(B, 64, 3, generator=g), dim=-1)
    grids = _cell_grids(B, seed)[:, None] if m.cfg.evidence_cells else [None] * B
    with torch.inference_mode():
        prefix = [m.condition(pts[i:i + 1], nrm[i:i + 1]) for i in range(B)]
        evidence = [m.point_evidence(pts[i:i + 1], nrm[i:i + 1], grids[i]) for i in range(B)]
    return prefix, evidence


class _Spy:
    """A decoder that records the batch of every decode step."""

    def __init__(self, dec):
        self.dec, self.cfg, self.batches = dec, dec.cfg, []
        if hasattr(dec, "new_cache"):
            self.new_cache = dec.new_cache

    def prefill(self, *a):
        return self.dec.prefill(*a)

    def decode_step(self, tokens, block, pos, cache):
        self.batches.append(tokens.shape[0])
        return self.dec.decode_step(tokens, block, pos, cache)


@pytest.mark.parametrize("backend", ["torch", "onnx"])
@pytest.mark.parametrize("temperature,top_k,cells,counts", [(1.0, 0, False, False), (0.7, 20, False, False),
                                                           (1.0, 0, True, False), (1.0, 0, True, True)])
def test_batch_rows_equal_each_seed_decoded_alone(backend, temperature, top_k, cells, counts):
    m = _model(1, cells, counts)
    dec = _Spy(OrtDecoder(m) if backend == "onnx" else m)
    prefix, evidence = _inputs(m, 1)
    cfg = SamplingConfig(temperature=temperature, top_k=top_k, top_p=0.95, max_vertices=12, seed=7)
    batch = generate(dec, torch.cat(prefix), cfg, evidence=StackedEvidence(evidence))
    steps = list(dec.batches)
    alone = [generate(dec, prefix[k], SamplingConfig(**{**cfg.__dict__, "seed": 7 + k}), evidence=evidence[k])[0]
             for k in range(B)]
    assert [r.tolist() for r in batch] == [r.tolist() for r in alone]
    lengths = [len(r) for r in alone]
    assert len(set(lengths)) > 1 and all(r[-1] == vt.EOS for r in alone)  # rows finish at different steps
    # A finished row leaves the batch: a row of L tokens is in L - 2 decode steps (BOS is prefilled,
    # nothing is decoded after EOS).
    assert steps[0] == B and steps == sorted(steps, reverse=True)
    assert sum(steps) == sum(lengths) - 2 * B and len(steps) == max(lengths) - 2


def test_onnx_batch_rows_are_computed_as_alone_before_and_after_finished_rows_leave():
    m = _model(2)
    dec = OrtDecoder(m)
    assert sorted(dec.sessions) == [1, 2]  # batch 1 and the default candidates' batch, exported at load
    cache = dec.new_cache(4, 40, "cpu", torch.float32)
    assert sorted(dec.sessions) == [1, 2, 4] and isinstance(cache, NumpyCache)
    assert cache.buf.shape == (2 * m.cfg.depth, 40, 4 * m.cfg.dim)
    prefix, _ = _inputs(m, 2)
    alone = [dec.new_cache(1, 40, "cpu", torch.float32) for _ in range(4)]
    tok = torch.tensor([[vt.BLOCK0 + 9], [vt.OFFSET0 + 99], [vt.BLOCK0 + 300], [vt.OFFSET0 + 7]])
    blk = torch.tensor([[9], [5], [300], [40]])
    pos = prefix[0].shape[1] + 1

    def step(rows, at):
        """(batched logits of the sequences `rows`, the same decoded alone) at position `at`."""
        got = dec.decode_step(tok[rows], blk[rows], at, cache)
        want = torch.cat([dec.decode_step(tok[k:k + 1], blk[k:k + 1], at, alone[k]) for k in rows])
        return got, want

    with torch.inference_mode():
        first = torch.full((4, 1), vt.BOS)
        dec.prefill(torch.cat(prefix), first, cache)
        for k in range(4):
            dec.prefill(prefix[k], first[k:k + 1], alone[k])
        got, want = step([0, 1, 2, 3], pos)
        assert torch.equal(got, want)  # bit for bit: each row computed as it is alone
        cache.select(torch.tensor([3, 0, 2]))  # no graph of 3: the slot of sequence 1 stays, unread
        assert cache.slots == 4
        got, want = step([3, 0, 2], pos + 1)
        assert torch.equal(got, want)
        cache.select(torch.tensor([2, 1]))  # positions in (3, 0, 2): sequences 2 and 0, down to the graph of 2
        assert cache.slots == 2 and cache.buf.shape[-1] == 2 * m.cfg.dim
        got, want = step([2, 0], pos + 2)
        assert torch.equal(got, want)


def test_pipeline_candidates_are_each_seed_alone(monkeypatch):
    """Every candidate (not only the chosen one) is the mesh its seed gives alone, scored as before."""
    import fastmesh.pipeline.result as fp

    # Candidates are scored before the whole step; the random networks' strays would be pulled in after it, and
    # those the rest covers dropped.
    monkeypatch.setattr(fp, "pull_in", lambda vertices, surface, limit: (vertices, np.zeros(len(vertices), bool)))
    monkeypatch.setattr(fp, "pull_in_uncrossed",  # the solid face stage's result is pulled in this way
                        lambda vertices, faces, surface, limit: (vertices, np.zeros(len(vertices), bool)))
    drop = fp.drop_strays
    monkeypatch.setattr(fp, "drop_strays", lambda vertices, faces, keep, surface=None: drop(vertices, faces, keep))
    pipe = Pipeline.random(seed=0)
    shape = point_cloud(primitive("l_block"), 4000)  # its points: the block's own 20 faces would come back
    # Open: a closed block's points are rebuilt from its planes, with no candidates decoded.
    params = dict(max_vertices=24, temperature=1.0, closed="false")
    both = pipe.generate(shape, GenerateParams(seed=11, candidates=2, **params))
    norm = Normalization.fit(shape.vertices)
    reference = input_surface(shape, norm.apply(shape.vertices), pipe.triangle_config.support_points, 11)
    fits = []
    for k in range(2):
        alone = pipe.generate(shape, GenerateParams(seed=11 + k, candidates=1, **params))
        fits.append(round(weighed_fit(norm.apply(alone.vertices), alone.faces, reference, 11), 6))
        if both.info["chosen_seed"] == 11 + k:
            assert np.allclose(both.vertices, alone.vertices) and np.array_equal(both.faces, alone.faces)
            assert both.tokens == alone.tokens
    assert both.info["fits"] == pytest.approx(fits, abs=2e-6)


def _kind(tokens: torch.Tensor) -> torch.Tensor:
    return torch.where(tokens < vt.BLOCK0, 0, torch.where(tokens < vt.OFFSET0, 1, 2))


def test_the_kind_of_the_next_token_is_the_decoders_and_the_cell_weight_only_picks_among_offsets():
    """``choose_next``: the kind (EOS / block / offset) is drawn from the decoder's probability mass of each kind at
    ``structure_temperature``, before the offset bias is looked at; the bias then decides which offset."""
    from fastmesh.models.generate import choose_next

    g = torch.Generator().manual_seed(0)
    logits = torch.randn(1, vt.VOCAB_SIZE, generator=g) * 2
    logits[0, vt.PAD] = logits[0, vt.BOS] = float("-inf")
    favourite = torch.zeros(1, vt.N_OFFSETS)
    favourite[0, 1234] = 100.0  # an offset the bias makes certain once an offset is chosen
    cfg = SamplingConfig(temperature=0.3, top_k=50, top_p=0.95, structure_temperature=1.0)
    plain = torch.cat([choose_next(logits, cfg, [torch.Generator().manual_seed(s)]) for s in range(3000)])
    biased = torch.cat([choose_next(logits, cfg, [torch.Generator().manual_seed(s)], favourite) for s in range(3000)])
    assert torch.equal(_kind(plain), _kind(biased))  # same draws: the bias never moves the kind
    assert (biased[_kind(biased) == 2] == vt.OFFSET0 + 1234).all()
    p = logits.softmax(-1)[0]
    want = torch.stack([p[:vt.BLOCK0].sum(), p[vt.BLOCK0:vt.OFFSET0].sum(), p[vt.OFFSET0:].sum()])
    got = torch.bincount(_kind(plain), minlength=3) / len(plain)
    assert (got - want).abs().max() < 0.03, (got, want)
    # Greedy: the kind with the most mass, then the best token of that kind.
    greedy = choose_next(logits, SamplingConfig(temperature=0), None, favourite)
    assert int(_kind(greedy)) == int(want.argmax())


def test_pacing_closes_the_block_once_the_sequence_runs_ahead_of_the_cells():
    """With ``pace``, no sequence stays in a block (another offset after an offset) once its vertices reach
    pace x the cells' expected vertices up to that block + PACE_SLACK; without it the same decoder stays on."""
    from fastmesh.models.choice import PACE_SLACK

    m, prefix, evidence = _crowded()
    seen = {True: 0, False: 0}
    for pace in (0.0, 0.5):
        cfg = SamplingConfig(temperature=0, max_vertices=100, pace=pace)
        seqs = generate(m, torch.cat(prefix), cfg, evidence=StackedEvidence(evidence))
        for row, ev in zip(seqs, evidence, strict=True):
            n, block = 0, -1
            for prev, tok in zip(row[:-1].tolist(), row[1:].tolist(), strict=True):
                if vt.BLOCK0 <= tok < vt.OFFSET0:
                    block = tok - vt.BLOCK0
                stays = prev >= vt.OFFSET0 and tok >= vt.OFFSET0
                if stays:
                    over = n >= float(ev.expected_through(torch.tensor([block]), 0.5)) + PACE_SLACK
                    seen[pace > 0] += over
                n += tok >= vt.OFFSET0
    assert seen[True] == 0 and seen[False] > 0


def test_stacked_count_reading_equals_each_row_read_alone():
    """``StackedEvidence.count_bias`` reads all rows at once; each row must read what its own evidence gives,
    rows with and without a face-count target mixed."""
    m = _model(3, cells=True, counts=True)
    g = torch.Generator().manual_seed(3)
    pts = torch.rand(B, 64, 3, generator=g) - 0.5
    nrm = torch.nn.functional.normalize(torch.randn(B, 64, 3, generator=g), dim=-1)
    grids = _cell_grids(B, 3)[:, None]
    targets = [None, torch.tensor([40]), None, torch.tensor([300])]
    with torch.inference_mode():
        evidence = [m.point_evidence(pts[i:i + 1], nrm[i:i + 1], grids[i], targets[i]) for i in range(B)]
    stacked = StackedEvidence(evidence)
    for step in range(5):  # the stacked inputs are made on the first reading and kept
        block = torch.randint(-1, vt.N_BLOCKS, (B, 1), generator=g)
        offset = torch.randint(-1, 4096, (B, 1), generator=g)
        n_vert = torch.randint(0, 400, (B, 1), generator=g)
        n_in_block = torch.randint(0, 70, (B, 1), generator=g)
        eos, stay = stacked.count_bias(block, offset, n_vert, n_in_block)
        for i, ev in enumerate(evidence):
            e1, s1 = ev.count_bias(block[i:i + 1], offset[i:i + 1], n_vert[i:i + 1], n_in_block[i:i + 1])
            assert torch.equal(eos[i:i + 1], e1) and torch.equal(stay[i:i + 1], s1), (step, i)
    assert eos.abs().sum() > 0 and stay.abs().sum() > 0


def _crowded():
    """A decoder with cell evidence, as if trained, and B shapes whose cells crowd into one block each: it goes
    to the block the cells fill, takes its cells (likelier in sequence order) and ends when they are done."""
    from fastmesh.models.cells import FLOOR
    from fastmesh.tokenizer.grid import LEVELS, sort_key

    m = _model(2, cells=True)
    with torch.no_grad():
        m.evidence.cell_gain.fill_(10.0)
        m.evidence.cell_block_table.weight[6:] = 1.0  # 64 or more expected vertices
        m.evidence.cell_eos_table.weight[1:] = -1.0  # vertices expected ahead
    g = torch.Generator().manual_seed(2)
    pts = torch.rand(B, 64, 3, generator=g) - 0.5
    nrm = torch.nn.functional.normalize(torch.randn(B, 64, 3, generator=g), dim=-1)
    prefix, evidence = [], []
    for i in range(B):  # 80 likely cells in one block, likelier in sequence order: the decoder stays there
        grid = torch.full((1, LEVELS ** 3), FLOOR)
        cells = torch.randint(16 * i, 16 * i + 16, (80, 3), generator=g).unique(dim=0)
        cells = cells[sort_key(cells).argsort()]
        grid[0, flat_index(cells)] = 8.0 - 0.1 * torch.arange(len(cells))
        with torch.inference_mode():
            prefix.append(m.condition(pts[i:i + 1], nrm[i:i + 1]))
            evidence.append(m.point_evidence(pts[i:i + 1], nrm[i:i + 1], grid))
    return m, prefix, evidence


def test_pace_and_cell_weight_apply_to_the_cells_own_estimate_and_leave_a_target_as_asked():
    """``expected_through(block, pace)``: pace x the cells' expected vertices up to the block, but a face-count
    target's share of them unscaled (the target is the count asked for, not an estimate to correct);
    ``weighted_cells(block, w)``: (w - 1) x the offsets' cell term, nothing with a target."""
    m = _model(3, cells=True, counts=True)
    g = torch.Generator().manual_seed(4)
    pts = torch.rand(2, 64, 3, generator=g) - 0.5
    nrm = torch.nn.functional.normalize(torch.randn(2, 64, 3, generator=g), dim=-1)
    grids = _cell_grids(2, 4)
    block = torch.tensor([300, 300])
    with torch.inference_mode():
        own = m.point_evidence(pts, nrm, grids)
        asked = m.point_evidence(pts, nrm, grids, torch.tensor([500, 500]))
    full, paced = own.expected_through(block), own.expected_through(block, 0.8)
    assert float(full.min()) > 0 and torch.allclose(paced, 0.8 * full)
    assert torch.equal(asked.expected_through(block, 0.8), asked.expected_through(block))
    assert not torch.allclose(asked.expected_through(block), full)  # scaled to the target
    term = own.offset_cells(block)
    assert term.abs().sum() > 0 and torch.equal(own.weighted_cells(block, 6.0), term * 5.0)
    assert not asked.weighted_cells(block, 6.0).any()
