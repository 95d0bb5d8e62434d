"""Static-shape decoding (``models.decode``) against its slow twins: the eager loop at temperature 0, a per-token
uncached reference of the same counter-based sampling, each row decoded alone, and the full-cache (graph) path
against the windowed one; on CUDA (``-m gpu``) the captured graph against the same steps run eagerly."""

from __future__ import annotations

import pytest
import torch
from test_batched_decode import B, _crowded, _inputs, _model
from test_cells import _cell_grids

from fastmesh.models import static_step
from fastmesh.models.decode import StaticDecoder, stack_evidence
from fastmesh.models.generate import (
    Cancelled,
    SamplingConfig,
    StackedEvidence,
    generate,
    pace_mask,
)
from fastmesh.models.sampling import MASK32, choose_static, gumbel, hash32, seed_key
from fastmesh.models.vertex import grammar_mask, grammar_state
from fastmesh.tokenizer import vertex as vt

torch.set_num_threads(1)
CUDA = torch.cuda.is_available()


@torch.inference_mode()
def reference(m, prefix, cfg: SamplingConfig, evidence, seed: int) -> list[int]:
    """One shape decoded alone, one token at a time, each step a full uncached pass of the decoder (which adds the
    evidence and count bias and the grammar mask itself) and the draw of ``sampling.choose_static``."""
    keys = torch.tensor([seed_key(seed)])
    cells = evidence is not None and evidence.reads_logodds
    tokens = torch.tensor([[vt.BOS]])
    for step in range(1, 2 * cfg.max_vertices + 2):
        logits = m(tokens, prefix=prefix, evidence=evidence)[:, -1]
        n_vert = (tokens >= vt.OFFSET0).sum(1)
        block, offset = (x[:, -1] for x in grammar_state(tokens))
        mask = grammar_mask(tokens[:, -1], block, offset, eos_only=n_vert >= cfg.max_vertices)
        if cells and cfg.pace > 0:
            mask[:, vt.OFFSET0:] &= ~pace_mask(evidence.expected_through(block, cfg.pace), tokens[:, -1],
                                               n_vert)[:, None]
        bias = evidence.weighted_cells(block, cfg.cell_weight) if cells else None
        nxt, stuck = choose_static(logits.masked_fill(~mask, float("-inf")), cfg, keys, torch.tensor([step]), bias)
        assert not stuck.any()
        tokens = torch.cat([tokens, nxt[:, None]], dim=1)
        if int(nxt) == vt.EOS:
            break
    return tokens[0].tolist()


def _cfg(**kw) -> SamplingConfig:
    return SamplingConfig(**{"max_vertices": 12, "seed": 7, **kw})


def test_the_hash_is_the_same_on_integers_and_tensors_and_its_draws_follow_the_probabilities():
    xs = [0, 1, 2, 12345, 2**31 - 1, 2**31, MASK32]
    assert hash32(torch.tensor(xs)).tolist() == [hash32(x) for x in xs]
    assert all(0 <= hash32(x) <= MASK32 for x in xs) and len({hash32(x) for x in xs}) == len(xs)
    assert seed_key(7) != seed_key(7 + 2**32)  # both halves of a seed count
    # Gumbel-max over 4000 steps of one row: each of 4 tokens as often as its probability says.
    p = torch.tensor([0.1, 0.2, 0.3, 0.4])
    ids = torch.arange(4)
    keys = torch.tensor([seed_key(3)])
    picks = (p.log() + gumbel(keys, torch.arange(4000), 1, ids)).argmax(-1)  # the steps broadcast as rows
    assert (torch.bincount(picks, minlength=4) / 4000 - p).abs().max() < 0.03
    # Another stream, step or seed: other noise.
    a = gumbel(keys, torch.tensor([5]), 1, ids)
    for other in (gumbel(keys, torch.tensor([5]), 0, ids), gumbel(keys, torch.tensor([6]), 1, ids),
                  gumbel(torch.tensor([seed_key(4)]), torch.tensor([5]), 1, ids)):
        assert not torch.equal(a, other)


@pytest.mark.parametrize("cells,counts", [(False, False), (True, False), (True, True)])
def test_greedy_static_decoding_gives_the_eager_loops_tokens(cells, counts):
    m = _model(1, cells, counts)
    prefix, evidence = _inputs(m, 1)
    cfg = _cfg(temperature=0)
    eager = generate(m, torch.cat(prefix), cfg, evidence=StackedEvidence(evidence))
    static = generate(StaticDecoder(m), torch.cat(prefix), cfg, evidence=StackedEvidence(evidence))
    assert [r.tolist() for r in static] == [r.tolist() for r in eager]
    assert len({len(r) for r in eager}) > 1  # rows that end at different steps


@pytest.mark.parametrize("temperature,top_k,top_p,cells,counts", [
    (1.0, 0, 1.0, False, False), (0.7, 20, 0.9, False, False), (1.0, 0, 0.95, True, False),
    (0.3, 50, 0.95, True, True), (0.5, 10, 0.8, True, True)])
def test_sampled_rows_are_the_slow_reference_of_each_seed_alone(temperature, top_k, top_p, cells, counts):
    m = _model(2, cells, counts)
    prefix, evidence = _inputs(m, 2)
    cfg = _cfg(temperature=temperature, top_k=top_k, top_p=top_p)
    static = generate(StaticDecoder(m), torch.cat(prefix), cfg, evidence=StackedEvidence(evidence))
    want = [reference(m, prefix[k], cfg, evidence[k], cfg.seed + k) for k in range(B)]
    assert [r.tolist() for r in static] == want
    assert len({tuple(r) for r in want}) == B and all(r[-1] == vt.EOS for r in want)


def test_the_pace_holds_in_the_static_loop():
    """The pace mask as the eager loop applies it (``test_batched_decode``'s crowded shapes)."""
    m, prefix, evidence = _crowded()
    for kw in (dict(pace=0.5), dict(pace=0.0)):
        cfg = SamplingConfig(temperature=0, max_vertices=100, **kw)
        eager = generate(m, torch.cat(prefix), cfg, evidence=StackedEvidence(evidence))
        static = generate(StaticDecoder(m), torch.cat(prefix), cfg, evidence=StackedEvidence(evidence))
        assert [r.tolist() for r in static] == [r.tolist() for r in eager]


def test_the_full_cache_under_a_mask_gives_the_windowed_tokens_and_buffers_serve_the_next_call():
    """The graph's code path (whole cache, masked, the evidence's table of every block) run eagerly equals the
    CPU's (windowed attention, the current blocks' evidence at every step); a decoder's buffers, reused by a later
    call with other shapes' inputs, give what a fresh decoder gives."""
    m = _model(3, True, True)
    prefix, evidence = (x[:2] for x in _inputs(m, 3))  # two shapes: tabling every block costs on a CPU
    prefix2, evidence2 = (x[:2] for x in _inputs(m, 4))
    cfg = _cfg(temperature=1.0, top_k=0, top_p=0.95)
    full, windowed = StaticDecoder(m, window=False, table=True), StaticDecoder(m, window=True, table=False)
    a = generate(full, torch.cat(prefix), cfg, evidence=StackedEvidence(evidence))
    assert [r.tolist() for r in a] == [r.tolist() for r in generate(windowed, torch.cat(prefix), cfg,
                                                                    evidence=StackedEvidence(evidence))]
    second = generate(full, torch.cat(prefix2), cfg, evidence=StackedEvidence(evidence2))
    fresh = generate(StaticDecoder(m, window=False, table=True), torch.cat(prefix2), cfg,
                     evidence=StackedEvidence(evidence2))
    assert [r.tolist() for r in second] == [r.tolist() for r in fresh] != [r.tolist() for r in a]
    assert len(full._batches) == 1  # one shape, one set of buffers
    assert [r.tolist() for r in a] == [r.tolist() for r in generate(full, torch.cat(prefix), cfg,
                                                                    evidence=StackedEvidence(evidence))]


def test_seeds_per_row_and_a_stacked_evidence_read_as_its_rows():
    m = _model(4, True, True)
    prefix, evidence = _inputs(m, 5)
    cfg = _cfg(temperature=1.0)
    dec = StaticDecoder(m)
    rows = dec.generate(torch.cat(prefix), cfg, evidence=StackedEvidence(evidence), seeds=[40, 3, 40, 9])
    assert rows[0].tolist() == dec.generate(prefix[0], cfg, evidence=evidence[0], seeds=[40])[0].tolist()
    assert rows[3].tolist() == dec.generate(prefix[3], _cfg(temperature=1.0, seed=9), evidence=evidence[3])[0].tolist()
    stacked = stack_evidence(evidence)
    assert torch.equal(stacked.logodds[2], evidence[2].logodds[0]) and len(stacked.levels) == len(evidence[0].levels)
    with pytest.raises(ValueError, match="seeds"):
        dec.generate(torch.cat(prefix), cfg, evidence=StackedEvidence(evidence), seeds=[1])


def test_progress_and_cancel_at_the_checks_and_a_row_with_no_finite_logit_fails_clearly():
    m = _model(5)
    prefix, evidence = _inputs(m, 6)
    seen = []
    cfg = _cfg(temperature=1.0, max_vertices=30)
    generate(StaticDecoder(m), torch.cat(prefix), cfg, evidence=StackedEvidence(evidence),
             progress=lambda step, n: seen.append((step, n)), progress_every=4)
    assert seen and all(step % 4 == 0 for step, _ in seen) and seen == sorted(seen)
    with pytest.raises(Cancelled):
        generate(StaticDecoder(m), torch.cat(prefix), cfg, evidence=StackedEvidence(evidence),
                 should_cancel=lambda: True)
    # A row the caller stops ends there (no EOS); the others go on as they would.
    whole = StaticDecoder(m).generate(torch.cat(prefix), cfg, evidence=StackedEvidence(evidence))
    cut = StaticDecoder(m).generate(torch.cat(prefix), cfg, evidence=StackedEvidence(evidence), progress_every=4,
                                    rows=lambda step, n: [k == 1 for k in range(B)])
    assert len(cut[1]) == 5 and cut[1].tolist() == whole[1][:5].tolist() and vt.EOS not in cut[1].tolist()
    assert [r.tolist() for k, r in enumerate(cut) if k != 1] == [r.tolist() for k, r in enumerate(whole) if k != 1]
    with torch.no_grad():
        m.head.weight.fill_(float("nan"))
    with pytest.raises(FloatingPointError, match="no token"):
        generate(StaticDecoder(m), torch.cat(prefix), cfg, evidence=StackedEvidence(evidence))


@pytest.mark.parametrize("temperature", [0.0, 1.0])
def test_the_compiled_step_gives_the_eager_steps_tokens(temperature):
    """The network's step fused by ``torch.compile`` (``FASTMESH_COMPILE=1`` on CUDA), run on this CPU, against the
    same static step run eagerly; a second call reuses the compiled program."""
    m = _model(8, True, True)
    prefix, evidence = _inputs(m, 9)
    cfg = _cfg(temperature=temperature, max_vertices=20)
    fused, eager = StaticDecoder(m, window=False, compiled=True), StaticDecoder(m, window=False, compiled=False)
    for _ in range(2):
        got = generate(fused, torch.cat(prefix), cfg, evidence=StackedEvidence(evidence))
        want = generate(eager, torch.cat(prefix), cfg, evidence=StackedEvidence(evidence))
        assert [r.tolist() for r in got] == [r.tolist() for r in want]
    assert next(iter(fused._batches.values())).fused is not None  # it compiled, not fell back


def test_a_step_that_fails_to_compile_runs_uncompiled(monkeypatch, caplog):
    m = _model(8, True, True)
    prefix, evidence = _inputs(m, 9)
    cfg = _cfg(temperature=1.0)

    def broken(*a, **k):
        raise RuntimeError("no compiler here")

    monkeypatch.setattr(static_step, "_FUSED", [broken])
    dec = StaticDecoder(m, window=False, compiled=True)
    got = generate(dec, torch.cat(prefix), cfg, evidence=StackedEvidence(evidence))
    want = generate(StaticDecoder(m, window=False), torch.cat(prefix), cfg, evidence=StackedEvidence(evidence))
    assert [r.tolist() for r in got] == [r.tolist() for r in want]
    assert next(iter(dec._batches.values())).fused is None and "compiling the decode step failed" in caplog.text


def test_capture_needs_cuda():
    if CUDA:
        pytest.skip("CUDA present: the captured path is tested under -m gpu")
    with pytest.raises(ValueError, match="CUDA"):
        StaticDecoder(_model(0), capture=True)


def _inputs_on(m, seed: int, device: str):
    """``test_batched_decode._inputs`` made on ``device``."""
    g = torch.Generator().manual_seed(seed)
    pts = (torch.rand(B, 64, 3, generator=g) - 0.5).to(device)
    nrm = torch.nn.functional.normalize(torch.randn(B, 64, 3, generator=g), dim=-1).to(device)
    grids = _cell_grids(B, seed)[:, None].to(device)
    with torch.inference_mode():
        prefix = [m.condition(pts[i:i + 1], nrm[i:i + 1]) for i in range(B)]
        evidence = [m.point_evidence(pts[i:i + 1], nrm[i:i + 1], grids[i]) for i in range(B)]
    return prefix, evidence


@pytest.mark.gpu
@pytest.mark.skipif(not CUDA, reason="needs CUDA")
@pytest.mark.parametrize("temperature", [0.0, 1.0])
@pytest.mark.parametrize("compiled", [False, True])
def test_cuda_graph_gives_the_eager_static_steps_tokens(temperature, compiled):
    """Three rows: the graph's batch is padded to four (a finished copy of row 0), the eager one is not; the
    captured step with the network's step compiled or as it is."""
    xs = torch.randint(0, 2**32, (4096,), generator=torch.Generator().manual_seed(0))
    assert torch.equal(hash32(xs.cuda()).cpu(), hash32(xs))  # int64 products wrap alike on both devices
    m = _model(6, True, True).cuda()
    prefix, evidence = (x[:3] for x in _inputs_on(m, 7, "cuda"))
    cfg = _cfg(temperature=temperature, max_vertices=40)
    graph, eager = StaticDecoder(m, capture=True, compiled=compiled), StaticDecoder(m, capture=False, compiled=False)
    for _ in range(2):  # the first call captures, the second replays the kept graph
        got = generate(graph, torch.cat(prefix), cfg, evidence=StackedEvidence(evidence))
        want = generate(eager, torch.cat(prefix), cfg, evidence=StackedEvidence(evidence))
        assert [r.tolist() for r in got] == [r.tolist() for r in want]
    batch = next(iter(graph._batches.values()))
    assert batch.graph is not None and batch.state["out"].shape[0] == 4 and (batch.fused is not None) == compiled
    if temperature == 0:  # and greedy, the eager loop's tokens on the same device
        assert [r.tolist() for r in got] == [r.tolist() for r in generate(m, torch.cat(prefix), cfg,
                                                                          evidence=StackedEvidence(evidence))]


def test_the_pipeline_decodes_with_static_shapes_when_asked_and_greedy_gives_the_eager_mesh(monkeypatch):
    from fastmesh.evaluation.primitives import point_cloud, primitive
    from fastmesh.models.onnx_decode import choose_decoder
    from fastmesh.params import GenerateParams
    from fastmesh.pipeline import Pipeline

    m = _model(0)
    monkeypatch.setenv("FASTMESH_DECODER", "static")
    assert isinstance(choose_decoder(m, "cpu"), StaticDecoder)
    static = Pipeline.random(seed=0)
    assert static.info()["decoder"] == "static"
    monkeypatch.setenv("FASTMESH_DECODER", "torch")
    eager = Pipeline.random(seed=0)
    shape = point_cloud(primitive("torus"), 3000)
    params = GenerateParams(seed=3, temperature=0, max_vertices=24, closed="false")
    a, b = static.generate(shape, params), eager.generate(shape, params)
    assert a.tokens == b.tokens > 10
    assert (a.vertices == b.vertices).all() and (a.faces == b.faces).all()
    sampled = static.generate(shape, GenerateParams(seed=3, max_vertices=24, closed="false", candidates=2))
    assert sampled.info["candidates"] == 2 and len(sampled.faces) > 0
