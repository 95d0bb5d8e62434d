"""Jobs batched in one process (``fastmesh.batch``, ``Pipeline.generate_batch``): each job's result, progress,
cancellation, timings and errors are what they are when it runs alone."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh
from test_batched_decode import _inputs, _model, _Spy

from fastmesh.batch import Batch
from fastmesh.evaluation.primitives import point_cloud, primitive
from fastmesh.models.generate import Cancelled, SamplingConfig, StackedEvidence, generate
from fastmesh.models.onnx_decode import OrtDecoder
from fastmesh.params import GenerateParams
from fastmesh.pipeline import STAGES, Pipeline
from fastmesh.request import TIMED_STAGES
from fastmesh.shapes.shape import Shape
from fastmesh.tokenizer import vertex as vt

torch.set_num_threads(1)
VERTICES_START = dict((name, lo) for name, lo, _ in STAGES)["vertices"]


@pytest.fixture(scope="module")
def pipe() -> Pipeline:
    return Pipeline.random(seed=0)


@pytest.fixture(autouse=True)
def _no_flat_path(monkeypatch):
    """The dense turned box would be simplified within its own faces (test_flat) with no frame decoded."""
    from fastmesh.pipeline import result as step8

    monkeypatch.setattr(step8, "flat_faced", lambda req: None)


def _sphere(scale: float = 3.0) -> Shape:
    m = trimesh.creation.icosphere(3)  # 1,280 faces: more than a tiny network's result (no low-poly input)
    return Shape(vertices=np.asarray(m.vertices) * scale + [10.0, -4.0, 2.0], faces=np.asarray(m.faces))


def _turned_box() -> Shape:
    """A box turned at an angle: made in its own frame and its canonical one, so it decodes twice."""
    box = trimesh.creation.box(extents=(3.0, 2.0, 1.0)).subdivide().subdivide()
    box.apply_transform(trimesh.transformations.rotation_matrix(0.6, [1.0, 2.0, 3.0]))
    return Shape(vertices=np.asarray(box.vertices), faces=np.asarray(box.faces))


def _jobs() -> list[tuple[Shape, GenerateParams]]:
    return [
        (_sphere(), GenerateParams(seed=1, max_vertices=24)),
        (point_cloud(primitive("torus"), 2000), GenerateParams(seed=7, max_vertices=24)),  # same sampling as 0
        (point_cloud(_sphere(1.5), 2000, seed=3),
         GenerateParams(seed=3, max_vertices=20, temperature=0.8, candidates=3)),  # other sampling: its own rows
        # Two decodings, the turned frame's kept (at this seed: which frame a random network's mesh wins varies).
        (_turned_box(), GenerateParams(seed=2, max_vertices=24, candidates=1, closed="false")),
        (_sphere(2.0), GenerateParams(seed=2, max_vertices=24, target_faces=40)),
        (point_cloud(primitive("box"), 2000), GenerateParams(seed=5, max_vertices=24)),  # planes: no decoding
        (_sphere(), GenerateParams(seed=0, max_vertices=10**6)),  # refused, as alone
    ]


def _alone(pipe: Pipeline, shape: Shape, params: GenerateParams, **kw):
    try:
        return pipe.generate(shape, params, **kw)
    except Exception as e:  # noqa: BLE001 - compared with the batch's outcome
        return e


def _assert_same(got, want) -> None:
    if isinstance(want, Exception):
        assert type(got) is type(want) and str(got) == str(want)
        return
    assert not isinstance(got, Exception), got
    assert np.array_equal(got.vertices, want.vertices) and np.array_equal(got.faces, want.faces)
    assert got.tokens == want.tokens and got.info == want.info and got.quality == want.quality


def test_a_batch_gives_each_job_exactly_what_it_gives_alone(pipe, monkeypatch):
    jobs = _jobs()
    alone = [_alone(pipe, s, p) for s, p in jobs]
    assert alone[3].info["turned_degrees"] > 0 and alone[5].info["result_from"] == "planes"
    assert isinstance(alone[6], ValueError)
    spy = _Spy(pipe.decoder)
    monkeypatch.setattr(pipe, "decoder", spy)
    batch = pipe.generate_batch([s for s, _ in jobs], [p for _, p in jobs])
    for got, want in zip(batch, alone, strict=True):
        _assert_same(got, want)
    # Jobs 0, 1, 3 and 4 share their sampling settings: 2 + 2 + 2 (job 3's one candidate in each of its two
    # frames, decoded as one request) + 2 candidates in one decoder batch.
    assert max(spy.batches) == 8
    assert set(batch[0].timings) == set(TIMED_STAGES) and batch[0].timings["vertices"] > 0


def test_jobs_join_the_next_round_and_each_keeps_its_progress_and_timings(pipe):
    """Continuous batching: a job added after a round joins the next one; each job's progress is its own,
    non-decreasing to 1."""
    jobs = _jobs()[:4]
    alone = [_alone(pipe, s, p) for s, p in jobs]
    seen: list[list[tuple[str, float]]] = [[] for _ in jobs]
    batch = Batch(pipe)

    def add(i):
        batch.add(i, pipe.steps(*jobs[i], progress=lambda stage, f, i=i: seen[i].append((stage, f))))

    add(0)
    add(1)
    batch.round()  # jobs 0 and 1 decode; then jobs 2 and 3 (both of job 3's frames at once) in the next round
    add(2)
    add(3)
    rounds = 1
    while len(batch):
        batch.round()
        rounds += 1
    done = batch.pop_done()
    assert sorted(done) == [0, 1, 2, 3] and rounds == 2 and batch.pop_done() == {}
    for i, want in enumerate(alone):
        _assert_same(done[i], want)
        fractions = [f for _, f in seen[i]]
        assert fractions == sorted(fractions) and fractions[-1] == 1.0
        assert any(stage == "vertices" and f > VERTICES_START for stage, f in seen[i])  # from its own rows


def test_a_cancelled_job_stops_and_the_others_go_on(pipe):
    jobs = [(_sphere(), GenerateParams(seed=s, max_vertices=40)) for s in (1, 2, 3)]
    alone = [_alone(pipe, s, p) for s, p in jobs]
    decoding = [False] * 3

    def progress(i):
        def report(stage, fraction):
            decoding[i] = decoding[i] or (stage == "vertices" and fraction > VERTICES_START)
        return report

    out = pipe.generate_batch([s for s, _ in jobs], [p for _, p in jobs], [progress(i) for i in range(3)],
                              [None, lambda: decoding[1], None])  # job 1 cancelled once its rows decode
    assert isinstance(out[1], Cancelled)
    _assert_same(out[0], alone[0])
    _assert_same(out[2], alone[2])


def test_an_error_in_one_job_stays_that_jobs(pipe):
    """A job whose decoding raises (here its progress callback) fails alone; its batch is decoded again
    without it and the others come out as they do alone."""
    jobs = [(_sphere(), GenerateParams(seed=s, max_vertices=24)) for s in (1, 2, 3)]
    alone = [_alone(pipe, s, p) for s, p in jobs]

    def boom(stage, fraction):
        if stage == "vertices" and fraction > VERTICES_START:
            raise RuntimeError("boom")

    out = pipe.generate_batch([s for s, _ in jobs], [p for _, p in jobs], [None, boom, None])
    assert isinstance(out[1], RuntimeError) and str(out[1]) == "boom"
    _assert_same(out[0], alone[0])
    _assert_same(out[2], alone[2])


def test_a_fatal_error_stops_the_whole_batch(pipe):
    """After an error that leaves the process unusable (a CUDA error) nothing more runs: every job of the decoding
    that raised it has the error (which row caused it cannot be told), the batch is failed, and its other jobs
    are left for ``close``."""
    jobs = [(_sphere(), GenerateParams(seed=s, max_vertices=24, temperature=t)) for s, t in ((1, 0.3), (2, 0.3),
                                                                                           (3, 0.5))]

    def poisoned(stage, fraction):
        if stage == "vertices" and fraction > VERTICES_START:
            raise RuntimeError("CUDA error: device-side assert triggered")

    batch = Batch(pipe, fatal=lambda e: "CUDA error" in str(e))
    for i, (shape, params) in enumerate(jobs):
        batch.add(i, pipe.steps(shape, params, progress=poisoned if i == 1 else None))
    batch.round()
    assert batch.failed is not None and "CUDA error" in str(batch.failed)
    done = batch.pop_done()
    assert sorted(done) == [0, 1] and all("CUDA error" in str(e) for e in done.values())
    batch.round()  # runs nothing more
    assert batch.pop_done() == {}
    assert batch.close() == [2] and len(batch) == 0  # job 2 (other sampling) was not decoded


def test_generate_batch_needs_one_params_per_shape(pipe):
    with pytest.raises(ValueError, match="as many params"):
        pipe.generate_batch([_sphere(), _sphere()], [GenerateParams()])


def test_rows_stopped_by_the_caller_leave_the_others_as_they_are():
    m = _model(1, cells=True, counts=True)
    dec = OrtDecoder(m)
    prefix, evidence = _inputs(m, 1)
    cfg = SamplingConfig(temperature=1.0, top_k=0, max_vertices=30, seed=7)
    full = generate(dec, torch.cat(prefix), cfg, evidence=StackedEvidence(evidence))
    counts = []

    def rows(step, n_vert):
        counts.append(list(n_vert))
        return [False, step >= 8, False, False]

    cut = generate(dec, torch.cat(prefix), cfg, evidence=StackedEvidence(evidence), rows=rows, progress_every=4)
    assert [cut[k].tolist() for k in (0, 2, 3)] == [full[k].tolist() for k in (0, 2, 3)]
    assert len(full[1]) > 9  # row 1 stops at step 8: BOS and the 8 tokens it had
    assert len(cut[1]) == 9 and cut[1].tolist() == full[1][:9].tolist()
    assert counts[0] == [int((full[k][:5] >= vt.OFFSET0).sum()) for k in range(4)]  # each row's own count


def test_seeds_are_given_per_row():
    m = _model(2)
    dec = OrtDecoder(m)
    prefix, evidence = _inputs(m, 2)
    cfg = SamplingConfig(temperature=1.0, top_k=0, max_vertices=12, seed=0)
    both = generate(dec, torch.cat(prefix[:2]), cfg, evidence=StackedEvidence(evidence[:2]), seeds=[41, 5])
    for k, seed in enumerate((41, 5)):
        alone = generate(dec, prefix[k], SamplingConfig(**{**cfg.__dict__, "seed": seed}), evidence=evidence[k])
        assert both[k].tolist() == alone[0].tolist()
    with pytest.raises(ValueError, match="one per prefix row"):
        generate(dec, torch.cat(prefix[:2]), cfg, seeds=[1])
    with pytest.raises(ValueError, match="seed"):
        generate(dec, torch.cat(prefix[:2]), cfg, seeds=[1, -1])


def test_shipped_weights_batched_as_alone():
    """The shipped decoder (cell evidence, counts, ONNX Runtime steps): two jobs' four candidates in one batch
    give each job's mesh alone."""
    pipe = Pipeline.from_pretrained()
    jobs = [(point_cloud(primitive("torus"), 4000), GenerateParams(seed=3, max_vertices=60)),
            (point_cloud(_sphere(), 4000, seed=1), GenerateParams(seed=8, max_vertices=60))]
    alone = [_alone(pipe, s, p) for s, p in jobs]
    spy = _Spy(pipe.decoder)
    pipe.decoder = spy
    for got, want in zip(pipe.generate_batch([s for s, _ in jobs], [p for _, p in jobs]), alone, strict=True):
        assert want.tokens > 0
        _assert_same(got, want)
    assert max(spy.batches) == 4
