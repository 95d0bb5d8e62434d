"""README as a new user reads it: its commands run as printed from a checkout after ``make run`` (the CLI is in
``.venv/bin``, not on the PATH), and its result tables say what docs/results.md measured."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
RESULTS = (ROOT / "docs" / "results.md").read_text()
# What `make run` and `make test` put in .venv/bin and nowhere else.
VENV_COMMANDS = ("fastmesh", "fastmesh-worker", "python", "pytest")


def _shell_blocks(text: str) -> list[str]:
    return re.findall(r"```sh\n(.*?)```", text, re.S)


def _table(text: str, header_start: str) -> list[dict[str, str]]:
    """The rows of the Markdown table whose header row starts with ``header_start``, each cell under its header
    (bold marks dropped)."""
    def cells(line: str) -> list[str]:
        return [c.strip().replace("**", "") for c in line.strip().strip("|").split("|")]

    lines = text[text.index(header_start):].splitlines()
    header = cells(lines[0])
    rows = []
    for line in lines[2:]:
        if not line.startswith("|"):
            break
        rows.append(dict(zip(header, cells(line), strict=True)))
    return rows


def _percent(share: str) -> str:
    return f"{round(100 * float(share))} %"


def test_readme_commands_call_the_cli_from_the_venv():
    bare = []
    for block in _shell_blocks(README):
        for line in block.splitlines():
            for word in VENV_COMMANDS:
                if re.search(rf"(^|[;&|!(]\s*|\$\(\s*|^while\s+!\s*){re.escape(word)}([\s;]|$)", line.strip()):
                    bare.append(line.strip())
    assert bare == [], "commands that are not on the PATH after `make run`:\n" + "\n".join(bare)
    assert ". .venv/bin/activate" in README  # and how to have them there


def _shares(cell: str) -> str:
    precision, recall = cell.split(" / ")
    return f"{_percent(precision)} / {_percent(recall)}"


def test_readme_point_cloud_table_is_the_one_measured():
    """README's point-cloud table is results.md's run of the 60 with the anchors, row for row (its code before
    left out), in every column the two share."""
    readme = _table(README, "| system | CD % | HD % |")
    measured = [row for row in _table(RESULTS, "| system (60 shapes) |")
                if not row["system (60 shapes)"].startswith("FastMesh before")]
    assert len(readme) == len(measured) >= 4

    def column(row: dict[str, str], start: str) -> str:
        return next(value for key, value in row.items() if key.startswith(start))

    for ours, theirs in zip(readme, measured, strict=True):
        for start in ("CD %", "HD %", "vertices within 1 cell", "back faces seen", "silhouette IoU", "edge-manifold"):
            assert column(ours, start) == column(theirs, start), (start, ours, theirs)
        assert column(ours, "normal angle") == column(theirs, "normal angle"), (ours, theirs)
        assert column(ours, "results with crossing") == column(theirs, "with crossing faces"), (ours, theirs)
        assert column(ours, "watertight") == column(theirs, "watertight"), (ours, theirs)


def test_readme_mesh_input_table_is_the_one_measured():
    readme = _table(README, "| system (mesh inputs) |")
    measured = _table(RESULTS, "| system (mesh inputs) |")
    assert len(readme) == len(measured) >= 3
    shares = next(k for k in readme[0] if k.startswith("vertices within 1 cell"))
    for ours, theirs in zip(readme, measured, strict=True):
        assert (ours["CD %"], ours["HD %"]) == (theirs["CD %"], theirs["HD %"]), (ours, theirs)
        assert ours[shares] == _shares(theirs["P@1 / R@1"]), (ours, theirs)


def test_readme_names_precision_and_recall():
    """Two shares of vertices found (46 % and 37 %) once stood side by side without saying which was which."""
    for header in ("| system | CD % | HD % |", "| system (mesh inputs) |"):
        assert "precision / recall" in README[README.index(header):].splitlines()[0], header


def _section(text: str, heading: str) -> str:
    start = text.index(f"\n## {heading}\n")
    end = text.find("\n## ", start + 1)
    return text[start:end if end >= 0 else len(text)]


def test_readme_explains_every_figure_of_the_quality_report(weights):
    """Each key of a real result's ``quality`` (quads asked for, so theirs too) has a row in README's Quality
    report: a pipeline deciding what to keep reads what each figure means there."""
    import trimesh

    from fastmesh.pipeline import GenerateParams, Pipeline
    from fastmesh.shapes.io import load_shape

    box = trimesh.creation.box(extents=(1.0, 2.0, 0.5)).export(file_type="obj").encode()
    result = Pipeline.from_pretrained(weights).generate(load_shape(box, filename="box.obj"),
                                                        GenerateParams(topology="quad", candidates=1))
    rows = _table(_section(README, "Quality report"), "| figure |")
    explained = {name.strip("` ") for row in rows for name in row["figure"].split(",")}
    assert set(result.quality) - explained == set(), "quality figures README does not explain"
    assert explained - set(result.quality) == set(), "README explains figures the report does not have"
