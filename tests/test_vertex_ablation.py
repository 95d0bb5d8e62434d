"""benchmarks/vertex_ablation.py: the decoder without the cell evidence runs with the other networks of the pipeline."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

from fastmesh.models.checkpoint import save_model
from fastmesh.pipeline import Pipeline, default_weights_dir

ROOT = Path(__file__).resolve().parents[1]


def _ablation():
    spec = importlib.util.spec_from_file_location("vertex_ablation", ROOT / "benchmarks" / "vertex_ablation.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_without_takes_a_decoder_folder_and_keeps_the_rest_of_the_pipeline(tmp_path):
    ablation = _ablation()
    pipe = Pipeline.from_pretrained()
    # A decoder that reads the point tables but not the cell evidence, as checkpoints/vertex-no-cells does (that
    # one is kept in git history only: docs/training.md).
    save_model(Pipeline.random("tiny").vertex, "vertex", tmp_path / "no-cells")
    other = ablation._without(str(tmp_path / "no-cells"), pipe)
    assert not other.vertex.cfg.evidence_cells and pipe.vertex.cfg.evidence_cells
    assert other.face is pipe.face and other.enhancer is pipe.enhancer and other.cell_net is pipe.cell_net
    assert other.fit_config == pipe.fit_config and other.triangle_config == pipe.triangle_config
    with pytest.raises(SystemExit, match="reads the cell evidence"):
        ablation._without(str(default_weights_dir() / "vertex"), pipe)
