"""`fastmesh train` end to end on a tiny cache: all three networks, exact resume, 2-process DDP."""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.numpy import load_file

from fastmesh.cli import main
from fastmesh.models.checkpoint import load_model
from fastmesh.tokenizer import quantize
from fastmesh.tokenizer.grid import LEVELS, N_CELLS
from fastmesh.training.augment import apply_symmetry, grid_symmetry, symmetric_cells
from fastmesh.training.data import build_dataset, load_dataset
from fastmesh.training.tasks import dense_cells, sparse_cells

CORPUS = Path(__file__).resolve().parents[2] / "shared" / "corpus"
N_MESHES = 10

ENC = {"dim": 32, "n_latents": 4, "depth": 0, "heads": 2, "n_points": 64, "n_freqs": 4}
TINY = {
    "vertex": {"model": {"dim": 32, "depth": 1, "heads": 2, "encoder": ENC}, "batch_cost": 600},
    "enhancer": {"model": {"dim": 32, "depth": 1, "heads": 2, "n_freqs": 4, "encoder": ENC}, "batch_cost": 300},
    "face": {"model": {"dim": 32, "depth": 1, "heads": 2, "edge_heads": 4, "edge_mlp_hidden": 8, "pair_chunk": 32,
                       "n_freqs": 4, "encoder": ENC}, "batch_cost": 40000},
    "cells": {"model": {"hidden": 16, "depth": 1, "n_points": 512}, "batch_cost": 2},
}
# warmup longer than any run here: the learning rate then does not depend on ``steps``, so
# "3 steps, then resume to 6" and "6 steps" follow the same schedule.
COMMON = {"max_batch": 4, "steps": 4, "warmup": 10, "log_every": 1, "eval_every": 2, "ckpt_every": 2,
          "val_batches": 1, "threads": 1, "seed": 7}


def _small_corpus_files() -> list[Path]:
    with open(CORPUS / "manifest.csv", newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if r.get("kind", "mesh") == "mesh" and 20 <= int(r["vertices"]) <= 120]
    return [CORPUS / r["file"] for r in sorted(rows, key=lambda r: r["file"])[:N_MESHES]]


def _synthetic_meshes(root: Path) -> None:
    """Fallback when ../shared/corpus is absent: primitives of varied shape."""
    import trimesh

    rng = np.random.default_rng(0)
    for i in range(N_MESHES):
        m = [trimesh.creation.icosphere(1), trimesh.creation.box(), trimesh.creation.cylinder(0.5, 1.0, sections=12),
             trimesh.creation.cone(0.5, 1.0, sections=10)][i % 4]
        m.apply_scale(rng.uniform(0.5, 1.5, 3))
        m.export(root / f"shape{i}.ply")


@pytest.fixture(scope="module")
def cache(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("train") / "meshes"
    root.mkdir()
    if (CORPUS / "manifest.csv").exists():
        for f in _small_corpus_files():
            shutil.copy(f, root / f.name)
    else:
        _synthetic_meshes(root)
    out = root.parent / "cache.npz"
    build_dataset([str(root)], out, max_vertices=1000, val_fraction=0.4, workers=1)
    ds = load_dataset(out)
    assert len(ds.indices("train")) >= 3 and len(ds.indices("val")) >= 1
    return out


def _config(tmp_path: Path, kind: str, **kw) -> Path:
    p = tmp_path / f"{kind}.json"
    p.write_text(json.dumps({**COMMON, **TINY[kind], **kw}))
    return p


def _log(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]


@pytest.mark.parametrize("kind", ["vertex", "enhancer", "face", "cells"])
def test_train_each_network(cache, tmp_path, kind):
    out = tmp_path / kind
    assert main(["train", kind, "--data", str(cache), "--out", str(out), "--config", str(_config(tmp_path, kind))]) == 0
    log = _log(out)
    steps = [r for r in log if "loss" in r]
    vals = [r["val"] for r in log if "val" in r]
    assert [r["step"] for r in steps] == [1, 2, 3, 4]
    assert all(np.isfinite(r["loss"]) for r in steps) and len(vals) == 2
    if kind == "face":  # the task's own validation metrics are logged
        assert {"precision", "recall", "f1"} <= set(vals[-1])
    if kind == "cells":
        assert {"precision_1", "recall_1"} <= set(vals[-1])
    model, meta = load_model(out)
    assert meta["kind"] == kind and meta["train"]["step"] == 4
    assert (out / "best" / "model.safetensors").exists() and (out / "train_state.pt").exists()


def test_face_model_with_pair_evidence_trains_on_perturbed_vertex_sets(cache, tmp_path):
    """The pair weights start at zero and move; a run that perturbs every sample sees other batches."""
    model = {**TINY["face"]["model"], "pair_evidence": True}
    rates = {"vertex_jitter": 0.2, "vertex_drop": 0.1, "vertex_extra": 0.1}
    losses = []
    for perturb in (0.0, 1.0):
        out = tmp_path / f"p{perturb}"
        cfg = _config(tmp_path, "face", model=model, augment={"perturb": perturb, **rates})
        assert main(["train", "face", "--data", str(cache), "--out", str(out), "--config", str(cfg)]) == 0
        net, meta = load_model(out)
        assert net.cfg.pair_evidence and meta["train"]["step"] == 4
        assert float(net.pair_fc.weight.detach().abs().sum()) > 0
        losses.append([r["loss"] for r in _log(out) if "loss" in r])
    assert losses[0] != losses[1]


@pytest.mark.parametrize("kind", ["face", "vertex"])
def test_resume_reproduces_an_uninterrupted_run(cache, tmp_path, kind):
    cfg = _config(tmp_path, kind)
    full, split = tmp_path / "full", tmp_path / "split"
    base = ["train", kind, "--data", str(cache), "--config", str(cfg)]
    assert main([*base, "--out", str(full), "--set", "steps=6"]) == 0
    assert main([*base, "--out", str(split), "--set", "steps=3"]) == 0
    assert main([*base, "--out", str(split), "--set", "steps=6", "--resume"]) == 0
    a, b = load_file(str(full / "model.safetensors")), load_file(str(split / "model.safetensors"))
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    # and the resumed run did train: weights moved since step 3 (the log continues at step 4)
    assert [r["step"] for r in _log(split) if "loss" in r] == [1, 2, 3, 4, 5, 6]


def test_torchrun_two_processes(cache, tmp_path):
    out = tmp_path / "ddp"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
           "-m", "fastmesh.cli", "train", "face", "--data", str(cache), "--out", str(out),
           "--config", str(_config(tmp_path, "face", steps=3))]
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    log = _log(out)
    assert [x["step"] for x in log if "loss" in x] == [1, 2, 3]  # rank 0 logs alone
    assert load_model(out)[1]["train"]["step"] == 3


def test_init_starts_from_saved_weights(cache, tmp_path):
    """--init continues from a saved network (its config too) and refuses a network of another kind."""
    first, second = tmp_path / "first", tmp_path / "second"
    cfg = _config(tmp_path, "vertex")
    assert main(["train", "vertex", "--data", str(cache), "--out", str(first), "--config", str(cfg),
                 "--set", "steps=2"]) == 0
    # Zero steps of learning rate: the weights must come out exactly as they went in.
    assert main(["train", "vertex", "--data", str(cache), "--out", str(second), "--config", str(cfg),
                 "--init", str(first), "--set", "steps=1", "--set", "lr=0.0"]) == 0
    a, b = load_file(str(first / "model.safetensors")), load_file(str(second / "model.safetensors"))
    assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)
    assert main(["train", "face", "--data", str(cache), "--out", str(tmp_path / "x"), "--init", str(first),
                 "--config", str(_config(tmp_path, "face"))]) == 2


def test_init_with_a_new_architecture_keeps_the_tensors_that_fit(cache, tmp_path):
    """--init with a --config of another encoder: same-named, same-shaped tensors come from the saved network."""
    first, second = tmp_path / "first", tmp_path / "second"
    cfg = _config(tmp_path, "vertex")
    assert main(["train", "vertex", "--data", str(cache), "--out", str(first), "--config", str(cfg),
                 "--set", "steps=2"]) == 0
    d = json.loads(cfg.read_text())
    d["model"].setdefault("encoder", {})["anchors"] = 8
    cfg2 = tmp_path / "anchored.json"
    cfg2.write_text(json.dumps(d))
    assert main(["train", "vertex", "--data", str(cache), "--out", str(second), "--config", str(cfg2),
                 "--init", str(first), "--set", "steps=1", "--set", "lr=0.0"]) == 0
    a, b = load_file(str(first / "model.safetensors")), load_file(str(second / "model.safetensors"))
    assert "encoder.latents" in a and "encoder.latents" not in b
    shared = [k for k in b if k in a]
    assert len(shared) == len(b) and all(np.array_equal(a[k], b[k]) for k in shared)
    assert load_model(second)[0].cfg.encoder.anchors == 8


def test_vertex_validation_reports_how_much_the_condition_helps(cache):
    """cond_gain = loss with another mesh's points - loss with its own: finite, and exactly 0 for one shape twice."""
    from fastmesh.training.loop import load_train_config
    from fastmesh.training.tasks import VertexTask

    task, ds = VertexTask(), load_dataset(cache)
    # anchored: the prefix carries each shape's anchor cells, so even a random decoder's loss depends on it
    cfg = load_train_config(None, {"model": {**TINY["vertex"]["model"], "encoder": {**ENC, "anchors": 8}}})
    model = task.build_model(cfg.model).eval()
    every = np.arange(len(ds))
    gain = task.evaluate(model, ds, every, cfg, "cpu")["cond_gain"]
    assert np.isfinite(gain) and gain != 0.0
    same = np.full(4, every[0])  # the same mesh four times: swapping conditions changes nothing
    assert task.evaluate(model, ds, same, cfg, "cpu")["cond_gain"] == 0.0


def _cell_net(cache: Path, tmp_path: Path) -> Path:
    """A cell evidence network trained one step (its log-odds are what a cell cache stores)."""
    out = tmp_path / "cells"
    assert main(["train", "cells", "--data", str(cache), "--out", str(out),
                 "--config", str(_config(tmp_path, "cells", steps=1))]) == 0
    return out


def _cell_cache(cache: Path, cells_dir: Path, out: Path, *args: str) -> Path:
    """``fastmesh data cells`` of ``cache`` with ``cells_dir``'s network into ``out``."""
    assert main(["data", "cells", str(cache), "--weights", str(cells_dir), "-o", str(out), *args]) == 0
    return out


def test_decoder_reading_cell_evidence_trains_from_a_cell_cache(cache, tmp_path):
    """`fastmesh data cells` stores each mesh's cell log-odds; a decoder with evidence_cells (and the face-count
    token) trains on them, and refuses a cache without them."""
    cells_dir = _cell_net(cache, tmp_path)
    cell_cache = _cell_cache(cache, cells_dir, tmp_path / "with_cells.npz", "--train", "3", "--val", "1")
    ds = load_dataset(cell_cache)
    assert len(ds) == 4 and len(ds.indices("val")) == 1
    grid = ds.cell_logits(0)
    assert grid.shape == (N_CELLS,) and (grid > -12).sum() > 0
    # worker processes score the same meshes from the same samples
    twin = load_dataset(_cell_cache(cache, cells_dir, tmp_path / "pooled.npz", "--train", "3", "--val", "1",
                                    "--workers", "2"))
    for k in ("cell_flat", "cell_logit", "c_off", "q"):
        np.testing.assert_array_equal(ds.arrays[k], twin.arrays[k], err_msg=k)
    # a batch carries them sparse; spread out they are the stored grids
    sparse = sparse_cells(ds, [0, 2])
    dense = dense_cells(sparse["cell_flat"], sparse["cell_logit"])
    torch.testing.assert_close(dense, torch.stack([ds.cell_logits(0), ds.cell_logits(2)]), rtol=0, atol=0)
    model = {**TINY["vertex"]["model"], "evidence": True, "evidence_normals": True, "evidence_cells": True,
             "count_condition": True}
    cfg = _config(tmp_path, "vertex", model=model, steps=2)
    out = tmp_path / "vertex"
    assert main(["train", "vertex", "--data", str(cell_cache), "--out", str(out), "--config", str(cfg)]) == 0
    assert all(np.isfinite(r["loss"]) for r in _log(out) if "loss" in r)
    assert load_model(out)[0].evidence.cell_gain is not None
    assert main(["train", "vertex", "--data", str(cache), "--out", str(tmp_path / "no"), "--config", str(cfg)]) == 2


@pytest.mark.parametrize("kind", ["face", "vertex"])
def test_worker_processes_make_the_batches_of_an_in_process_run(cache, tmp_path, kind):
    """Batches made ahead by workers (``workers``) draw the same random numbers: the same weights come out."""
    cfg = _config(tmp_path, kind)
    outs = []
    for workers in (0, 2):
        out = tmp_path / f"w{workers}"
        assert main(["train", kind, "--data", str(cache), "--config", str(cfg), "--out", str(out),
                     "--set", f"workers={workers}", "--set", "steps=5"]) == 0
        outs.append(load_file(str(out / "model.safetensors")))
    for k in outs[0]:
        np.testing.assert_array_equal(outs[0][k], outs[1][k], err_msg=k)


def test_cube_symmetries_carry_cells_with_the_mesh():
    """A mesh under a symmetry of ``grid_symmetry`` quantises to the moved cells of the original: the stored cell
    evidence of a mesh is valid for its moved copy."""
    rng = np.random.default_rng(3)
    v = rng.uniform(-0.5, 0.5, (500, 3))
    frac = (v + 0.5) * LEVELS % 1
    v = v[((frac > 0.01) & (frac < 0.99)).all(1)]  # not on a cell boundary, where rounding may go either way
    seen = set()
    for _ in range(40):
        sym = grid_symmetry(rng)
        seen.add((tuple(sym[0]), tuple(sym[1])))
        np.testing.assert_array_equal(quantize(apply_symmetry(v, sym)), symmetric_cells(quantize(v), sym, LEVELS))
    assert len(seen) > 20  # many of the 48, not one


def test_sparse_cells_move_with_the_mesh_under_a_symmetry(cache, tmp_path):
    """A batch's cells under a symmetry are the stored grid with its cells moved by it."""
    ds = load_dataset(_cell_cache(cache, _cell_net(cache, tmp_path), tmp_path / "with_cells.npz", "--train", "1",
                                  "--val", "0"))
    sym = grid_symmetry(np.random.default_rng(5))
    moved = sparse_cells(ds, [0], [sym])
    grid = dense_cells(moved["cell_flat"], moved["cell_logit"])[0].reshape(LEVELS, LEVELS, LEVELS)
    stored = ds.cell_logits(0).reshape(LEVELS, LEVELS, LEVELS)
    hot = torch.nonzero(stored > -12)
    to = torch.from_numpy(symmetric_cells(hot.numpy(), sym, LEVELS))
    torch.testing.assert_close(grid[to[:, 0], to[:, 1], to[:, 2]], stored[hot[:, 0], hot[:, 1], hot[:, 2]])
    assert int((grid > -12).sum()) == len(hot)
