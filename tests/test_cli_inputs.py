"""``fastmesh generate``'s INPUT and OUTPUT: a format that contradicts the output file is refused, and a folder
is read as a person keeps one (notes beside the shapes, the results of the last run, ``--glob``)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from stack import sphere_points, xyz_bytes

from fastmesh.cli import main
from fastmesh.cli.inputs import first_row_is_a_point, folder_jobs, generate_jobs

README = b"Shapes for the chair project.\nRun: fastmesh generate . -o .\n"


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "fastmesh.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=300)


@pytest.fixture()
def folder(tmp_path) -> Path:
    """Two shapes, a note and a picture, and a shape in a subfolder."""
    d = tmp_path / "shapes"
    (d / "sub").mkdir(parents=True)
    (d / "ball.xyz").write_bytes(xyz_bytes(sphere_points(200)))
    trimesh.creation.box().export(d / "box.obj")
    trimesh.creation.icosphere(1).export(d / "sub" / "ico.ply")
    (d / "readme.txt").write_bytes(README)
    (d / "photo.png").write_bytes(b"\x89PNG\r\n\x1a\n")
    return d


def _names(jobs, root: Path) -> list[str]:
    return [str(src.relative_to(root)) for src, _, _ in jobs]


@pytest.mark.parametrize("output, fmt", [("x.obj", "glb"), ("x.glb", "ply"), ("x.PLY", "obj")])
def test_a_format_that_contradicts_the_output_file_is_refused(tmp_path, capsys, output, fmt):
    src = tmp_path / "box.obj"
    trimesh.creation.box().export(src)
    code = main(["generate", str(src), "-o", str(tmp_path / output), "--format", fmt])
    err = capsys.readouterr().err
    assert code == 2 and f"--format {fmt} does not match the output file" in err, err
    assert f"name it x.{fmt}" in err and "Traceback" not in err
    assert not (tmp_path / output).exists()


def test_a_format_that_agrees_or_an_output_without_an_extension_is_taken(tmp_path):
    src = tmp_path / "box.obj"
    trimesh.creation.box().export(src)
    for output, fmt, made in (("x.obj", "obj", "obj"), ("x.OBJ", "obj", "obj"), ("x.obj", None, "obj"),
                              ("x", "ply", "ply"), ("x", None, "glb")):
        jobs, skipped = generate_jobs(str(src), str(tmp_path / output), fmt, None)
        assert jobs == [(src, tmp_path / output, made)] and skipped == []


@pytest.mark.parametrize("output, fmt", [("x.stl", None), ("x.fbx", None), ("x.STL", None), ("x.gltf", None),
                                         ("x.mesh", "ply"), ("x.stl", "glb")])
def test_an_output_named_for_a_format_we_do_not_write_is_refused(tmp_path, output, fmt):
    """``-o x.stl`` once wrote GLB bytes under that name and exited 0; ``submit`` refused the same name."""
    src = tmp_path / "box.obj"
    trimesh.creation.box().export(src)
    with pytest.raises(ValueError, match=r"must end in \.glb, \.obj or \.ply \(the formats written\)") as e:
        generate_jobs(str(src), str(tmp_path / output), fmt, None)
    assert f"not {Path(output).suffix}" in str(e.value)


def test_a_folder_as_the_output_of_one_file_is_refused(tmp_path):
    src = tmp_path / "box.obj"
    trimesh.creation.box().export(src)
    (tmp_path / "out.v2").mkdir()
    for out in (tmp_path, tmp_path / "out.v2"):
        with pytest.raises(ValueError, match="it is a folder; name the output file"):
            generate_jobs(str(src), str(out), None, None)


@pytest.mark.parametrize("verb", ["generate", "submit"])
def test_generate_and_submit_refuse_an_stl_output_alike(tmp_path, capsys, verb):
    """Exit 2 and one line naming the formats written, before any network loads (``--weights`` names no folder)
    or any request is sent (nothing listens at ``--url``); nothing is written."""
    src = tmp_path / "box.obj"
    trimesh.creation.box().export(src)
    out = tmp_path / "box.stl"
    extra = ["--weights", str(tmp_path / "no-weights")] if verb == "generate" else ["--url", "http://127.0.0.1:9"]
    code = main([verb, str(src), "-o", str(out), *extra])
    err = capsys.readouterr().err
    assert code == 2, err
    assert err == (f"fastmesh {verb}: error: cannot write {out}: the output must end in .glb, .obj or .ply (the "
                   f"formats written), not .stl; name it box.glb\n")
    assert not out.exists()


def test_folder_skips_notes_and_keeps_every_shape(folder, tmp_path):
    jobs, skipped = folder_jobs(folder, tmp_path / "out", None, None)
    assert _names(jobs, folder) == ["ball.xyz", "box.obj", "sub/ico.ply"]
    assert [(p.name, why) for p, why in skipped] == [
        ("readme.txt", "not a point file (its first line is not 3 or 6 numbers)")]
    assert [dst for _, dst, _ in jobs] == [tmp_path / "out" / n for n in ("ball.xyz.glb", "box.obj.glb",
                                                                         "sub/ico.ply.glb")]


def test_text_point_files_are_told_from_notes_by_their_first_row(tmp_path):
    cases = {b"# scan 3\n\n1 2 3\n": True, b"1,2,3,0,0,1\n": True, b"\r\n  0.5 1e-3 -2\r\n": True,
             README: False, b"x y z\n1 2 3\n": False, b"1 2\n": False, b"# only a comment\n": False, b"": False}
    for i, (data, point) in enumerate(cases.items()):
        (tmp_path / f"{i}.txt").write_bytes(data)
        assert first_row_is_a_point(tmp_path / f"{i}.txt") is point, data


def test_folder_results_are_not_inputs_of_the_next_run(folder):
    for name in ("ball.xyz.glb", "box.obj.obj", "box.obj.glb.glb", "sub/ico.ply.ply"):
        (folder / name).write_bytes(b"a result")
    jobs, skipped = folder_jobs(folder, folder, "glb", None)
    assert _names(jobs, folder) == ["ball.xyz", "box.obj", "sub/ico.ply"]
    assert sorted(str(p.relative_to(folder)) for p, why in skipped if "this tool's output" in why) == [
        "ball.xyz.glb", "box.obj.glb.glb", "box.obj.obj", "sub/ico.ply.ply"]
    # a file named like a result whose shape is not beside it is an input
    (folder / "ball.xyz").unlink()
    assert "ball.xyz.glb" in _names(folder_jobs(folder, folder, "obj", None)[0], folder)


def test_results_in_a_folder_inside_the_input_are_not_inputs(folder):
    (folder / "out").mkdir()
    (folder / "out" / "box.obj.glb").write_bytes(b"a result")
    (folder / "out" / "lone.ply").write_bytes(b"ply")
    jobs, _ = folder_jobs(folder, folder / "out", None, None)
    assert _names(jobs, folder) == ["ball.xyz", "box.obj", "sub/ico.ply"]


def test_glob_chooses_the_files(folder):
    assert _names(folder_jobs(folder, folder, None, "*.obj")[0], folder) == ["box.obj"]
    assert _names(folder_jobs(folder, folder, None, "**/*.ply")[0], folder) == ["sub/ico.ply"]
    assert _names(folder_jobs(folder, folder, None, "sub/*")[0], folder) == ["sub/ico.ply"]
    with pytest.raises(ValueError, match=r"no readable shapes in .* matching '\*\.stl'"):
        folder_jobs(folder, folder, None, "*.stl")
    with pytest.raises(ValueError, match="--glob chooses files in a folder"):
        generate_jobs(str(folder / "box.obj"), str(folder / "x.glb"), None, "*.obj")


def test_a_result_that_would_overwrite_an_input_is_refused(tmp_path):
    """OUTPUT above INPUT: ``in/in/q.ply``'s result would be ``in/q.ply.glb``, itself an input there."""
    src = tmp_path / "in"
    (src / "in").mkdir(parents=True)
    trimesh.creation.box().export(src / "in" / "q.ply")
    trimesh.creation.box().export(src / "q.ply.glb")
    with pytest.raises(ValueError, match="would overwrite an input"):
        folder_jobs(src, tmp_path, None, None)


def test_generate_into_its_own_folder_twice(folder, weights):
    """A note beside the shapes, then the first run's results beside them: both runs do the three shapes."""
    args = ("generate", folder, "-o", folder, "--weights", weights, "--max-vertices", "12", "--candidates", "1")
    first = _cli(*args)
    assert first.returncode == 0, first.stderr
    assert f"skipped {folder / 'readme.txt'}: not a point file" in first.stderr
    made = {p: p.read_bytes() for p in (folder / "ball.xyz.glb", folder / "box.obj.glb", folder / "sub/ico.ply.glb")}
    again = _cli(*args, "--glob", "**/*")
    assert again.returncode == 0, again.stderr
    assert f"skipped {folder / 'box.obj.glb'}: a result of box.obj (this tool's output)" in again.stderr
    assert again.stderr.count("[") == 3 and not list(folder.rglob("*.glb.glb"))
    assert all(p.read_bytes() == data for p, data in made.items())  # the same results, written again
    assert np.asarray(trimesh.load(folder / "box.obj.glb", force="mesh").faces).size > 0
