"""The device check (``make gpu-check`` runs ``pytest -m gpu``): the shipped pipeline on CUDA where there is one,
else on the CPU with fewer runs, so that everything but the CUDA kernels is tested before a GPU machine is used.

``FASTMESH_GPU_CHECK_RUNS`` sets the varied runs (default 100 on CUDA, 3 on a CPU); with
``FASTMESH_GPU_CHECK_RECORD`` set, their records (seconds, failures) are written there as JSON for
``benchmarks/gpu_check.py``.
"""

from __future__ import annotations

import copy
import json
import os
import statistics
import time
from dataclasses import replace

import numpy as np
import pytest
import torch
from gpu_inputs import smooth_cloud, varied

from fastmesh.models.generate import StackedEvidence, generate
from fastmesh.params import GenerateParams
from fastmesh.pipeline import Pipeline
from fastmesh.request import Frame
from fastmesh.shapes.shape import Normalization

pytestmark = pytest.mark.gpu
CUDA = torch.cuda.is_available()
DEVICE = "cuda" if CUDA else "cpu"
RUNS = int(os.environ.get("FASTMESH_GPU_CHECK_RUNS") or (100 if CUDA else 3))
QUALITY_INPUTS = 6 if CUDA else 2


@pytest.fixture(scope="module")
def pipe() -> Pipeline:
    return Pipeline.from_pretrained(device=DEVICE)


def run(pipe: Pipeline, name: str, shape, params: GenerateParams) -> dict:
    """One generate as a record: its seconds and result, or the error it raised (any error is a failure)."""
    if CUDA:
        torch.cuda.synchronize()
    t = time.perf_counter()
    try:
        r = pipe.generate(shape, params)
    except Exception as e:  # noqa: BLE001 - every error is a failure of the check, reported with its input
        return {"name": name, "ok": False, "s": time.perf_counter() - t, "error": f"{type(e).__name__}: {e}"}
    ok = len(r.faces) > 0 and bool(np.isfinite(r.vertices).all())
    return {"name": name, "ok": ok, "s": time.perf_counter() - t, "vertices": len(r.vertices),
            "faces": len(r.faces), "cd": r.quality["cd"], "timings": r.timings}


def test_varied_inputs_generate_without_a_failure(pipe):
    records, record = [], os.environ.get("FASTMESH_GPU_CHECK_RECORD")
    for name, shape, params in varied(RUNS):
        records.append(run(pipe, name, shape, params))
        if record:  # after every run: a check stopped by its time limit still leaves what it measured
            with open(record, "w") as f:
                json.dump({"device": str(pipe.device), "decoder": pipe.info()["decoder"], "runs": records}, f)
    failures = [r for r in records if not r["ok"]]
    assert not failures, failures[:5]


def _quality(p: Pipeline, inputs) -> tuple[list[float], list[int]]:
    cds, counts = [], []
    for name, shape, params in inputs:
        r = run(p, name, shape, params)
        assert r["ok"], r
        cds.append(r["cd"])
        counts.append(r["vertices"])
    return cds, counts


def test_the_device_and_the_cpu_give_results_of_the_same_quality(pipe, monkeypatch):
    """On fixed seeds, the device's pipeline (CUDA, static decoding captured as a graph) against the CPU's
    (ONNX Runtime's step): the draws differ by construction, so the same quality, not the same meshes.  Without
    CUDA, the CPU's static decoding against its default one."""
    inputs = [(f"quality-{i}", smooth_cloud(("ellipsoid", "wavy", "torus")[i % 3], 100 + i), GenerateParams(seed=i))
              for i in range(QUALITY_INPUTS)]
    if CUDA:
        other = Pipeline.from_pretrained(device="cpu")
    else:
        monkeypatch.setenv("FASTMESH_DECODER", "static")
        other = Pipeline.from_pretrained(device="cpu")
        assert other.info()["decoder"] == "static" and pipe.info()["decoder"] != "static"
    (cd_a, n_a), (cd_b, n_b) = _quality(pipe, inputs), _quality(other, inputs)
    for a, b in ((statistics.median(cd_a), statistics.median(cd_b)), (statistics.median(n_a), statistics.median(n_b))):
        assert a <= 1.5 * b + 0.3 and b <= 1.5 * a + 0.3, (cd_a, cd_b, n_a, n_b)


def _same(a, b) -> bool:
    if isinstance(a, Exception) or isinstance(b, Exception):
        return type(a) is type(b) and str(a) == str(b)
    return a.tokens == b.tokens and np.allclose(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces)


def test_a_batch_gives_each_job_what_it_gives_alone(pipe):
    """Jobs batched (``Pipeline.generate_batch``) against the same jobs one by one; a pipeline without a batch API
    decodes a job's candidates as one batch, each of which must be the sequence its seed gives alone."""
    if hasattr(pipe, "generate_batch"):
        jobs = [(s, p) for _, s, p in varied(4, seed=5)]
        batched = pipe.generate_batch([s for s, _ in jobs], [p for _, p in jobs])
        alone = []
        for s, p in jobs:
            try:
                alone.append(pipe.generate(s, p))
            except Exception as e:  # noqa: BLE001 - a job's error is its outcome, batched or not
                alone.append(e)
        assert all(_same(a, b) for a, b in zip(batched, alone, strict=True))
        return
    shape = smooth_cloud("wavy", 7)
    frame = Frame.of(shape)
    params = GenerateParams(seed=11, candidates=3)
    cells = pipe._logodds(frame)
    encoded = [pipe._encode(frame, params.seed + k, params, cells) for k in range(3)]
    prefix, evidence = [e[2] for e in encoded], [e[3] for e in encoded]
    cfg = params.sampling(pipe.max_vertices)
    batched = generate(pipe.decoder, torch.cat(prefix), cfg, evidence=StackedEvidence(evidence))
    alone = [generate(pipe.decoder, prefix[k], replace(cfg, seed=params.seed + k), evidence=evidence[k])[0]
             for k in range(3)]
    assert [t.tolist() for t in batched] == [t.tolist() for t in alone]
    assert len({len(t) for t in batched}) > 1  # three different sequences


@pytest.mark.skipif(not CUDA, reason="needs CUDA: the cell features computed on the device against the CPU's")
def test_the_cell_grid_on_the_device_matches_the_cpu(pipe):
    """The cell evidence (features and network) computed on CUDA, in float64 like on the CPU: the same candidate
    cells, log-odds equal up to rounding."""
    shape = smooth_cloud("wavy", 3)
    unit = Normalization.fit(shape.vertices).apply(shape.vertices).astype(np.float32)
    normals = shape.normals.astype(np.float32)
    on_device = pipe.cell_net.grid(unit, normals)
    on_cpu = copy.deepcopy(pipe.cell_net).cpu().grid(unit, normals)
    assert on_device.device.type == "cuda"
    assert torch.allclose(on_device.cpu(), on_cpu, atol=1e-3)
