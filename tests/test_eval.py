"""``fastmesh.evaluation.eval`` end to end: the vertex-stage metrics in the per-mesh rows and the summary."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from fastmesh.evaluation.eval import artist_vertices, evaluate_end_to_end, pair_inputs
from fastmesh.params import GenerateParams
from fastmesh.pipeline import Pipeline
from fastmesh.shapes.io import load_shape, sample_surface

torch.set_num_threads(1)


def _eval_set(folder, mesh: trimesh.Trimesh):
    """``mesh`` as a mesh input, a point-cloud input and the reference of both, in ``folder``."""
    (folder / "inputs").mkdir()
    (folder / "reference").mkdir()
    mesh.export(folder / "inputs" / "mesh.ply")
    pts, nrm = sample_surface(load_shape(folder / "inputs" / "mesh.ply"), 2048, seed=0)
    np.savez(folder / "inputs" / "cloud.npz", points=pts, normals=nrm)
    for name in ("mesh", "cloud"):
        mesh.export(folder / "reference" / f"{name}.ply")
    return folder


@pytest.fixture()
def box_set(tmp_path):
    """A box (not at the origin, not a cube) as a mesh input, a point-cloud input and a reference."""
    return _eval_set(tmp_path, trimesh.creation.box(extents=(4.0, 2.0, 1.0)).apply_translation((10.0, -3.0, 5.0)))


@pytest.fixture()
def sphere_set(tmp_path):
    """A sphere: a curved input, which the networks decode (a box is rebuilt from its planes without them)."""
    return _eval_set(tmp_path, trimesh.creation.icosphere(2, radius=2.0).apply_translation((10.0, -3.0, 5.0)))


def test_convex_hull_of_a_box_finds_every_artist_vertex(box_set):
    pairs = pair_inputs(box_set / "inputs", box_set / "reference")
    assert [p[0].name for p in pairs] == ["cloud.npz", "mesh.ply"]
    report = evaluate_end_to_end(Pipeline.random(seed=0), pairs, GenerateParams(max_vertices=16),
                                 systems=("fastmesh", "convex_hull"))
    hull = report["meshes"][1]["convex_hull"]["vertex_metrics"]  # the hull of the box mesh is its 8 corners
    assert hull == {"precision_1": 1.0, "precision_2": 1.0, "recall_1": 1.0, "recall_2": 1.0, "on_surface": 1.0,
                    "count_ratio": 1.0, "generated": 8, "reference": 8}
    cloud = report["meshes"][0]["convex_hull"]["vertex_metrics"]  # hull of samples: on the surface
    assert cloud["on_surface"] == 1.0 and cloud["reference"] == 8
    summary = report["summary"]["convex_hull"]["vertex_metrics"]
    assert summary["mean_recall_1"] == pytest.approx((1.0 + cloud["recall_1"]) / 2)
    assert summary["median_count_ratio"] == pytest.approx((1.0 + cloud["count_ratio"]) / 2)
    for row in report["meshes"]:  # the pipeline's own result is scored the same way
        vm = row["fastmesh"]["vertex_metrics"]
        assert vm["generated"] == row["fastmesh"]["vertices"]
        assert all(0.0 <= vm[k] <= 1.0 for k in ("precision_1", "precision_2", "recall_1", "recall_2", "on_surface"))
    assert set(report["summary"]["fastmesh"]["vertex_metrics"]) == {
        "mean_precision_1", "mean_precision_2", "mean_recall_1", "mean_recall_2", "mean_on_surface",
        "mean_count_ratio", "median_count_ratio"}


def test_mesh_inputs_are_set_beside_their_decimation_per_package(tmp_path):
    """A dense mesh input: its quadric decimation to our own face count is scored beside our result, and the
    summary (overall and per package) says how many results are closed, whole and open where."""
    sphere = trimesh.creation.icosphere(4)  # 5,120 faces
    for sub in ("inputs", "reference"):
        (tmp_path / sub).mkdir()
    for name in ("pkgA__ball", "pkgB__ball"):
        sphere.export(tmp_path / "inputs" / f"{name}.ply")
        trimesh.creation.icosphere(1).export(tmp_path / "reference" / f"{name}.ply")
    report = evaluate_end_to_end(Pipeline.random(seed=0), pair_inputs(tmp_path / "inputs", tmp_path / "reference"),
                                 GenerateParams(max_vertices=16), systems=("fastmesh", "decimation"))
    for row in report["meshes"]:
        ours, dec = row["fastmesh"], row["decimation"]
        assert abs(dec["faces"] - ours["faces"]) <= 2 and dec["watertight"] and dec["boundary_edges"] == 0
        assert row["reference"]["watertight"] and ours["boundary_edges"] >= 0
    assert set(report["by_package"]) == {"pkgA", "pkgB"}
    for system in ("fastmesh", "decimation"):
        whole = report["summary"][system]
        assert whole["meshes"] == 2 and report["by_package"]["pkgA"][system]["meshes"] == 1
        assert {"share_watertight", "share_pieces_within_reference", "median_boundary_edges",
                "median_boundary_edges_closed_references"} <= set(whole)
    assert report["summary"]["decimation"]["share_watertight"] == 1.0
    # Where each result comes from, counted (the tiny networks' pipeline does not weigh the decimation).
    assert report["summary"]["fastmesh"]["result_from"] == {"model": 2} and "result_from" not in report["summary"][
        "decimation"]
    assert report["summary"]["fastmesh"]["vertices_from"] == {"decoder": 2}


def test_artist_vertices_merge_per_cell_in_the_reference_frame(box_set):
    ref = load_shape(box_set / "reference" / "mesh.ply")
    # A second copy of each corner (a seam splits vertices): one artist vertex each.
    v = np.concatenate([ref.vertices, ref.vertices])
    dup = ref.__class__(vertices=v, faces=np.concatenate([ref.faces, ref.faces + 8]))
    a = artist_vertices(dup, load_shape(box_set / "inputs" / "cloud.npz"))
    assert len(a["reference"]) == 8
    assert np.allclose(np.abs(a["norm"].apply(ref.vertices)).max(0), [0.5, 0.25, 0.125])
    assert a["surface"][1] is not None  # a point-cloud input: the reference's triangles are the surface


def test_tuned_params_carry_sampling_overrides_and_refuse_unknown_or_bad_ones():
    """``TunedParams``: a request's fields as given, the decoder's settings overridden; what a request carries
    itself, unknown names and out-of-range values are refused before any work."""
    from fastmesh.params import SamplingConfig, TunedParams

    tuned = TunedParams({"snap_margin": 1.5, "pace": 1.0}, GenerateParams(seed=7, candidates=3))
    cfg = tuned.sampling(500)
    assert (tuned.seed, tuned.candidates, cfg.seed, cfg.max_vertices) == (7, 3, 7, 500)
    assert (cfg.snap_margin, cfg.pace, cfg.cell_weight) == (1.5, 1.0, SamplingConfig().cell_weight)
    for bad, match in (({"snap": 1}, "SamplingConfig fields"), ({"seed": 3}, "SamplingConfig fields"),
                       ({"snap_margin": -1}, "snap_margin"), ([1], "SamplingConfig fields")):
        with pytest.raises(ValueError, match=match):
            TunedParams(bad)


def test_eval_cli_measures_a_sampling_setting(sphere_set, capsys, monkeypatch):
    """``fastmesh eval --sampling``: the setting reaches the decoder (a bad one is a clear error, exit 2)."""
    import fastmesh.batch as fb
    from fastmesh.cli import main

    seen, decode = [], fb.generate
    monkeypatch.setattr(fb, "generate",
                        lambda model, prefix, cfg, **kw: seen.append(cfg) or decode(model, prefix, cfg, **kw))
    args = ["eval", "--inputs", str(sphere_set / "inputs"), "--reference", str(sphere_set / "reference"),
            "--limit", "1"]
    assert main([*args, "--sampling", '{"snap_margin": 1.0, "cell_weight": 2.0}']) == 0
    assert seen and (seen[0].snap_margin, seen[0].cell_weight) == (1.0, 2.0)
    assert main([*args, "--sampling", '{"cell_weight": 99}']) == 2
    assert "cell_weight" in capsys.readouterr().err
    assert main([*args, "--sampling", "{nope"]) == 2
