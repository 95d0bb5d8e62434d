"""Vertex decoder: cached decoding equals uncached decoding; sampled sequences obey the grammar."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fastmesh.models.encoder import EncoderConfig
from fastmesh.models.generate import SamplingConfig, generate, generate_uncached
from fastmesh.models.vertex import VertexConfig, VertexDecoder
from fastmesh.tokenizer import vertex as vt

torch.set_num_threads(1)


def _model(seed: int = 0) -> VertexDecoder:
    torch.manual_seed(seed)
    enc = EncoderConfig(n_points=64, n_latents=4, dim=32, depth=1, heads=2, n_freqs=4)
    m = VertexDecoder(VertexConfig(dim=32, depth=2, heads=2, encoder=enc)).eval()
    with torch.no_grad():  # spread the logits so greedy choices are not near-ties
        m.head.weight.normal_(0, 1.0)
        m.tok_emb.weight.normal_(0, 0.5)
    return m


def _prefix(m: VertexDecoder, b: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    pts = torch.rand(b, 64, 3, generator=g) - 0.5
    nrm = torch.nn.functional.normalize(torch.randn(b, 64, 3, generator=g), dim=-1)
    with torch.no_grad():
        return m.condition(pts, nrm)


def _trim(row: torch.Tensor) -> list[int]:
    row = row.tolist()
    return row[: row.index(vt.EOS) + 1] if vt.EOS in row else [t for t in row if t != vt.PAD]


@pytest.mark.parametrize("seed", [0, 1])
def test_cached_equals_uncached_at_temperature_zero(seed):
    m = _model(seed)
    prefix = _prefix(m, 3, seed)
    cached = generate(m, prefix, SamplingConfig(temperature=0, max_vertices=12))
    uncached = generate_uncached(m, prefix, max_vertices=12)
    assert len(cached) == 3
    for a, b in zip(cached, uncached, strict=True):
        assert a.tolist() == _trim(b)
    assert any(len(a) > 4 for a in cached)  # not trivially BOS EOS


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
