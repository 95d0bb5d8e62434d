"""README as a new user reads it: its commands run as printed from a checkout after ``make run`` (the CLI is in
``.venv/bin``, not on the PATH), and its result tables say what docs/results.md measured."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
RESULTS = (ROOT / "docs" / "results.md").read_text()
# What `make install` puts in .venv/bin and nowhere else.
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
    readme = _table(README, "| system | CD % | HD % |")
    measured = _table(RESULTS, "| system | CD % | HD % |")
    assert len(readme) == len(measured) >= 5
    shares = next(k for k in readme[0] if k.startswith("vertices within 1 cell"))
    closed = next(k for k in readme[0] if k.startswith("watertight"))
    for ours, theirs in zip(readme, measured, strict=True):
        assert (ours["CD %"], ours["HD %"]) == (theirs["CD %"], theirs["HD %"]), (ours, theirs)
        assert ours[shares] == _shares(theirs["P@1 / R@1"]), (ours, theirs)
        assert ours[closed] == theirs["watertight where the reference is"].split(" / ")[0], (ours, theirs)


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
