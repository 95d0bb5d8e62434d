"""Threads per stage: the vertex decoder on one whatever the pipeline's count, the other stages on that count."""

from __future__ import annotations

import torch

import fastmesh.batch as batch
from fastmesh.evaluation.primitives import point_cloud, primitive
from fastmesh.models.onnx_decode import OrtDecoder
from fastmesh.params import GenerateParams
from fastmesh.pipeline import Pipeline


def test_the_decoder_runs_on_one_thread_and_the_other_stages_on_the_pipelines_count(monkeypatch):
    seen = {}
    decode = batch.generate  # the pipeline's decoding runs there (fastmesh.batch)

    def generate(*a, **kw):
        seen["vertices"] = torch.get_num_threads()
        return decode(*a, **kw)

    monkeypatch.setattr(batch, "generate", generate)
    try:
        pipe = Pipeline.random(seed=0, threads=2)
        condition = pipe.vertex.condition

        def encode(*a, **kw):
            seen["encode"] = torch.get_num_threads()
            return condition(*a, **kw)

        monkeypatch.setattr(pipe.vertex, "condition", encode)
        assert not isinstance(pipe.decoder, OrtDecoder) or pipe.decoder.threads == 1
        pipe.generate(point_cloud(primitive("torus"), 2000), GenerateParams(max_vertices=16, closed="false"))
        assert seen == {"encode": 2, "vertices": 1} and torch.get_num_threads() == 2
        pipe.stage_threads = {}  # N everywhere: the decoder too
        pipe.generate(point_cloud(primitive("torus"), 2000), GenerateParams(max_vertices=16, closed="false"))
        assert seen["vertices"] == 2
    finally:
        torch.set_num_threads(1)  # process-wide: the other tests run on one
