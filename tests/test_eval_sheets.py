"""``fastmesh eval`` scores what a renderer shows for every system in one run, and ``--sheets`` draws each shape:
reference, ours and the classical anchor, back faces marked."""

from __future__ import annotations

import struct
import sys
import types

import numpy as np
import pytest
import torch
import trimesh

from fastmesh.evaluation.eval import evaluate_end_to_end, pair_inputs
from fastmesh.params import GenerateParams
from fastmesh.pipeline import Pipeline
from fastmesh.preview.sheet import BACK_COLOR, GAP, contact_sheet
from fastmesh.shapes.io import load_shape, sample_surface

torch.set_num_threads(1)
SIGHT = {"back_face_share", "silhouette_iou", "normal_angle", "misoriented_edges", "misoriented_area",
         "self_intersections", "unwelded_vertices", "unwelded_share", "faces_per_reference_face"}


def _png_size(path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


@pytest.fixture()
def box_set(tmp_path):
    """A box as a mesh input and a point-cloud input, with the box as the reference of both."""
    box = trimesh.creation.box(extents=(4.0, 2.0, 1.0)).apply_translation((10.0, -3.0, 5.0))
    (tmp_path / "inputs").mkdir()
    (tmp_path / "reference").mkdir()
    box.export(tmp_path / "inputs" / "mesh.ply")
    pts, nrm = sample_surface(load_shape(tmp_path / "inputs" / "mesh.ply"), 2048, seed=0)
    np.savez(tmp_path / "inputs" / "cloud.npz", points=pts, normals=nrm)
    for name in ("mesh", "cloud"):
        box.export(tmp_path / "reference" / f"{name}.ply")
    return tmp_path


def test_every_system_is_scored_by_what_a_renderer_shows(box_set):
    pairs = pair_inputs(box_set / "inputs", box_set / "reference")
    report = evaluate_end_to_end(Pipeline.random(seed=0), pairs, GenerateParams(max_vertices=16),
                                 systems=("fastmesh", "convex_hull"), sheets=box_set / "sheets")
    for row in report["meshes"]:
        ref = row["reference"]
        assert ref["back_face_share"] < 1e-3 and ref["misoriented_edges"] == 0 and ref["self_intersections"] == 0
        for system in ("fastmesh", "convex_hull"):
            assert SIGHT <= set(row[system]) or row[system].get("failed")
        hull = row["convex_hull"]
        assert hull["back_face_share"] < 1e-3 and hull["misoriented_edges"] == 0 and hull["self_intersections"] == 0
        assert hull["faces_per_reference_face"] == hull["faces"] / 12
        if row["name"] == "mesh":  # the hull of the box's corners is the box: it shows what the box shows
            assert hull["silhouette_iou"] > 0.99 and hull["normal_angle"] < 0.5
        # one sheet a shape: 3 rows (reference, ours, the anchor) of 3 panels of 256 pixels
        assert _png_size(box_set / "sheets" / f"{row['name']}.png") == (3 * 256 + 2 * GAP, 3 * 256 + 2 * GAP)
    summary = report["summary"]["convex_hull"]
    assert summary["over_reference_back_faces"] == 0 and summary["with_misoriented_edges"] == 0
    assert {"mean_back_face_share", "mean_reference_back_face_share", "mean_silhouette_iou", "mean_normal_angle",
            "with_self_intersections", "with_unwelded_vertices", "mean_faces_per_reference_face"} <= set(summary)


def test_a_sheet_marks_back_faces_red():
    box = trimesh.creation.box()
    flipped = np.asarray(box.faces)[:, ::-1]
    img = contact_sheet([(box.vertices, box.faces), (box.vertices, flipped), None], size=64)
    assert img.shape == (3 * 64 + 2 * GAP, 3 * 64 + 2 * GAP, 3)
    rows = [img[r * (64 + GAP):r * (64 + GAP) + 64].reshape(-1, 3).astype(int) for r in range(3)]

    def red(px):  # pixels whose hue is the back faces' colour: red well above green and blue
        return int(((px[:, 0] > px[:, 1] + 60) & (px[:, 0] > px[:, 2] + 60)).sum())

    assert red(rows[0]) == 0 and red(rows[1]) > 0.2 * 64 * 64  # the inside-out box is red where it shows
    # a failed system: grey panels between the white rules
    assert BACK_COLOR[0] > BACK_COLOR[1] and {tuple(p) for p in rows[2]} == {(200, 200, 200), (255, 255, 255)}


def test_eval_cli_writes_sheets_with_the_anchor(box_set, monkeypatch, capsys):
    """``--sheets`` runs the anchor (Poisson + decimation to our count; a hull stands in for it here) and
    writes one picture per shape; without pymeshlab it is a clear error."""
    import fastmesh.evaluation.eval as ev
    from fastmesh.cli import main

    calls = []
    monkeypatch.setattr(ev, "poisson", lambda shape, faces, seed=0: calls.append(faces) or ev.convex_hull(shape))
    monkeypatch.setitem(sys.modules, "pymeshlab", types.ModuleType("pymeshlab"))
    args = ["eval", "--inputs", str(box_set / "inputs"), "--reference", str(box_set / "reference"), "--limit", "1",
            "--sheets", str(box_set / "sheets")]
    assert main(args) == 0 and len(calls) == 1
    assert "poisson_ours" in capsys.readouterr().out and (box_set / "sheets" / "cloud.png").exists()
    monkeypatch.setitem(sys.modules, "pymeshlab", None)  # import fails
    assert main(args) == 2 and "--sheets needs pymeshlab" in capsys.readouterr().err
