"""ONNX Runtime decode step: same tokens and logits as eager PyTorch, and the fallback to eager."""

from __future__ import annotations

import logging

import pytest
import torch

from fastmesh.models.encoder import EncoderConfig
from fastmesh.models.generate import SamplingConfig, generate
from fastmesh.models.kv_cache import KVCache
from fastmesh.models.onnx_decode import OrtDecoder, choose_decoder
from fastmesh.models.vertex import VertexConfig, VertexDecoder
from fastmesh.pipeline import Pipeline
from fastmesh.tokenizer import vertex as vt

pytest.importorskip("onnxruntime")
torch.set_num_threads(1)


def _model(seed: int = 0, anchors: int = 0) -> VertexDecoder:
    torch.manual_seed(seed)
    enc = EncoderConfig(n_points=64, n_latents=4, dim=32, depth=1, heads=2, n_freqs=4, anchors=anchors)
    m = VertexDecoder(VertexConfig(dim=32, depth=2, heads=2, encoder=enc)).eval()
    with torch.no_grad():  # spread the logits so greedy choices are not near-ties
        m.head.weight.normal_(0, 1.0)
        m.tok_emb.weight.normal_(0, 0.5)
        for e in (*m.cell_emb.tables, *m.block_emb.tables):  # make the grammar embeddings matter
            e.weight.normal_(0, 0.5)
    return m


def _prefix(m: VertexDecoder, b: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    pts = torch.rand(b, 64, 3, generator=g) - 0.5
    nrm = torch.nn.functional.normalize(torch.randn(b, 64, 3, generator=g), dim=-1)
    with torch.no_grad():
        return m.condition(pts, nrm)


@pytest.mark.parametrize("seed,anchors", [(0, 0), (1, 0), (0, 8)])
def test_greedy_generation_matches_eager_token_for_token(seed, anchors):
    m = _model(seed, anchors)
    dec = OrtDecoder(m)
    prefix = _prefix(m, 1, seed)
    cfg = SamplingConfig(temperature=0, max_vertices=12)
    ref = generate(m, prefix, cfg)[0].tolist()
    got = generate(dec, prefix, cfg)[0].tolist()
    assert got == ref
    assert len(ref) > 10 and ref[-1] == vt.EOS  # a real sequence, not BOS EOS


def test_sampled_generation_matches_eager():
    m = _model(2)
    dec = OrtDecoder(m)
    prefix = _prefix(m, 1, 2)
    cfg = SamplingConfig(temperature=1.0, top_k=20, top_p=0.9, max_vertices=12, seed=5)
    assert generate(dec, prefix, cfg)[0].tolist() == generate(m, prefix, cfg)[0].tolist()


def test_decode_step_logits_agree_along_a_sequence():
    m = _model(3, anchors=8)
    dec = OrtDecoder(m)
    prefix = _prefix(m, 1, 3)
    toks = [vt.BOS, vt.BLOCK0 + 77, vt.OFFSET0 + 1234, vt.OFFSET0 + 2345, vt.BLOCK0 + 300, vt.OFFSET0 + 5]
    block = [-1, 77, 77, 77, 300, 300]
    n = prefix.shape[1] + len(toks)
    ref_cache = KVCache(m.cfg.depth, 1, m.cfg.heads, n, m.cfg.head_dim)
    ort_cache = dec.new_cache(1, n, "cpu", torch.float32)
    with torch.inference_mode():
        first = torch.tensor([[toks[0]]])
        assert torch.equal(m.prefill(prefix, first, ref_cache), dec.prefill(prefix, first, ort_cache))
        for i in range(1, len(toks)):
            t, b = torch.tensor([[toks[i]]]), torch.tensor([[block[i]]])
            pos = prefix.shape[1] + i
            a = m.decode_step(t, b, pos, ref_cache)
            o = dec.decode_step(t, b, pos, ort_cache)
            assert o.shape == a.shape == (1, vt.VOCAB_SIZE) and o.dtype == torch.float32
            assert torch.allclose(o, a, atol=1e-4, rtol=1e-4), float((o - a).abs().max())
            assert a.std() > 0.1  # the comparison is not between two near-constant vectors
        with pytest.raises(IndexError):
            dec.decode_step(t, b, n, ort_cache)


def test_batch_above_one_runs_in_onnx_and_matches_eager():
    m = _model(0)
    dec = OrtDecoder(m)
    assert not isinstance(dec.new_cache(3, 8, "cpu", torch.float32), KVCache)  # the batched ONNX step runs it
    prefix = _prefix(m, 3, 0)
    cfg = SamplingConfig(temperature=0, max_vertices=12)
    got, ref = generate(dec, prefix, cfg), generate(m, prefix, cfg)
    assert [a.tolist() for a in got] == [b.tolist() for b in ref]


def test_choose_decoder_honours_the_environment(monkeypatch):
    m = _model(0)
    monkeypatch.setenv("FASTMESH_DECODER", "torch")
    assert choose_decoder(m, "cpu") is m
    monkeypatch.setenv("FASTMESH_DECODER", "onnx")
    assert isinstance(choose_decoder(m, "cpu"), OrtDecoder)
    monkeypatch.delenv("FASTMESH_DECODER")
    assert isinstance(choose_decoder(m, "cpu"), OrtDecoder)
    assert choose_decoder(m, "meta") is m  # not CPU: eager


def test_export_failure_falls_back_to_eager_with_a_warning(monkeypatch, caplog):
    def broken(*args, **kwargs):
        raise RuntimeError("exporter exploded")

    monkeypatch.setattr(torch.onnx, "export", broken)
    monkeypatch.setenv("FASTMESH_DECODER", "onnx")
    m = _model(0)
    with caplog.at_level(logging.WARNING, logger="fastmesh.models.onnx_decode"):
        assert choose_decoder(m, "cpu") is m
    assert "exporter exploded" in caplog.text
    # The pipeline keeps working on the eager path and says so.
    pipe = Pipeline.random(seed=0)
    assert pipe.info()["decoder"] == "torch"


@pytest.mark.parametrize("batch", [1, 2])
def test_a_wrong_export_is_caught_by_the_load_time_check(monkeypatch, caplog, batch):
    m = _model(0)
    real_init = OrtDecoder.__init__

    def init_then_break(self, model, threads=None):
        real_init(self, model, threads)
        assert sorted(self.sessions) == [1, 2]  # the default batch of candidates is exported at load
        run = self.sessions[batch].run
        self.sessions[batch] = type("S", (), {"run": lambda s, o, f: [x + 1.0 for x in run(o, f)]})()

    monkeypatch.setattr(OrtDecoder, "__init__", init_then_break)
    with caplog.at_level(logging.WARNING, logger="fastmesh.models.onnx_decode"):
        assert choose_decoder(m, "cpu") is m
    assert "differs from eager" in caplog.text


def test_pipeline_uses_onnx_by_default_and_torch_when_forced(monkeypatch):
    monkeypatch.delenv("FASTMESH_DECODER", raising=False)
    pipe = Pipeline.random(seed=0)
    assert pipe.info()["decoder"] == "onnx" and isinstance(pipe.decoder, OrtDecoder)
    monkeypatch.setenv("FASTMESH_DECODER", "torch")
    eager = Pipeline.random(seed=0)
    assert eager.info()["decoder"] == "torch" and eager.decoder is eager.vertex
