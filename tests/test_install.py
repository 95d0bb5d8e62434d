"""What ``make run`` and ``make test`` install: running takes the package and its dependencies only, testing adds
pyproject's ``dev`` extra, and nothing the service, the workers or the CLI import comes from that extra alone.

The Makefile is read through ``make -n`` (its recipes printed, none run) with ``VENV`` pointed at a folder of the
test's own, so the checkout's ``.venv`` is neither read nor changed.
"""

from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
from importlib import metadata
from pathlib import Path

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10: pip's copy of the same parser
    from pip._vendor import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]
PROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
# The packages `pip install .` installs: what ``make run`` starts and what users import.
PACKAGES = ("fastmesh", "fastmesh_jobs", "service", "worker")


def _make_n(target: str, venv: Path) -> list[str]:
    """The commands ``make TARGET`` would run with its virtualenv at ``venv`` (none is run)."""
    env = {k: v for k, v in os.environ.items() if k not in ("MAKEFLAGS", "MFLAGS", "MAKELEVEL", "VENV")}
    p = subprocess.run(["make", "-n", "-C", str(ROOT), target, f"VENV={venv}"], capture_output=True, text=True,
                       env=env, timeout=60)
    assert p.returncode == 0, p.stderr
    return p.stdout.splitlines()


def _installs(lines: list[str]) -> list[str]:
    """What each ``pip install`` of the project names: ``.`` or ``.[extra]``."""
    return [m.group(1) for line in lines if (m := re.search(r"pip install .*-e '?(\.[^' ]*)'?\s*$", line))]


def test_make_run_installs_the_package_without_the_test_tools(tmp_path):
    venv = tmp_path / "venv"
    assert _installs(_make_n("run", venv)) == ["."]
    assert _installs(_make_n("test", venv)) == [".", ".[dev]"]


def test_each_install_set_has_its_stamp(tmp_path):
    """After ``make run`` has installed, ``make test`` adds the ``dev`` extra alone; after ``make test``, neither
    installs again (until pyproject.toml changes)."""
    venv = tmp_path / "venv"
    venv.mkdir()
    (venv / ".installed-run").touch()
    assert _installs(_make_n("run", venv)) == []
    assert _installs(_make_n("test", venv)) == [".[dev]"]
    (venv / ".installed-test").touch()
    assert _installs(_make_n("test", venv)) == [] and _installs(_make_n("run", venv)) == []
    os.utime(venv / ".installed-run", (0, 0))  # older than pyproject.toml: both sets again
    assert _installs(_make_n("test", venv)) == [".", ".[dev]"]


def _closure(requirements: list[str]) -> set[str]:
    """The installed distributions ``requirements`` pull in, with their own dependencies (no extras)."""
    seen: set[str] = set()
    todo = [Requirement(r) for r in requirements]
    while todo:
        req = todo.pop()
        name = canonicalize_name(req.name)
        if name in seen or (req.marker and not req.marker.evaluate({"extra": ""})):
            continue
        seen.add(name)
        todo += [Requirement(r) for r in metadata.distribution(name).requires or []]
    return seen


def _modules(dists: set[str]) -> set[str]:
    """The top-level modules the installed distributions ``dists`` provide (``xatlas`` of
    ``xatlas.cpython-311-x86_64-linux-gnu.so``)."""
    names = set()
    for dist in dists:
        for f in metadata.distribution(dist).files or []:
            top = f.parts[0]
            if not top.endswith((".dist-info", ".pth")) and top not in ("..", "__pycache__"):
                names.add(top.split(".")[0])
    return names


def _third_party_imports() -> dict[str, str]:
    """Each top-level module the packages import that is neither the standard library's nor ours, with a file
    that imports it."""
    found = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, ast.Import):
                    names = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and node.level == 0:
                    names = [node.module]
                else:
                    continue
                for top in {n.split(".")[0] for n in names} - set(sys.stdlib_module_names) - set(PACKAGES):
                    found.setdefault(top, str(path.relative_to(ROOT)))
    return found


def test_nothing_the_service_imports_comes_from_the_test_tools_alone():
    """Every module the installed packages import is installed by ``pip install .`` (its dependencies and theirs),
    or is a non-``dev`` extra's, imported only by the verb that needs it (pymeshlab: ``eval --baseline``)."""
    extras = PROJECT["optional-dependencies"]
    runtime = _closure(PROJECT["dependencies"])
    dev_only = _closure(extras["dev"]) - runtime
    assert {"pytest", "ruff", "playwright", "schemathesis", "hypothesis"} <= dev_only
    other_extras = {canonicalize_name(Requirement(r).name).replace("-", "_")
                    for name, reqs in extras.items() if name != "dev" for r in reqs}
    provided = _modules(runtime) | other_extras
    missing = {m: f for m, f in _third_party_imports().items() if m not in provided}
    assert missing == {}, f"imported, but not installed by `make run` (add them to [project] dependencies): {missing}"
