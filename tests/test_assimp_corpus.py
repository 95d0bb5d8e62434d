"""Real files no one here wrote: every file of Debian's assimp-testmodels with an extension we accept is
uploaded to the real stack (tiny model) and must end in a result, a clear job failure or a clear 4xx;
none may crash (5xx, no answer, internal error, stuck job).  ``make test`` installs the package
(scripts/install-assimp-testmodels.sh); FASTMESH_ASSIMP_MODELS points elsewhere."""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

import pytest
from stack import DB, forget_run, make_settings, wp

from service.processes import ServedApp, local_redis

ROOT = Path(os.environ.get("FASTMESH_ASSIMP_MODELS", "/usr/share/assimp/models"))
SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "assimp_corpus.py"


def corpus_module():
    spec = importlib.util.spec_from_file_location("assimp_corpus", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def served(weights, tmp_path_factory):
    url, server = local_redis(DB)
    s = make_settings(url, "assimp", weights=weights, max_queue_depth=1000)
    app = ServedApp(s)
    worker = wp(s, "assimp-w", tmp_path_factory.mktemp("logs") / "w.log").wait_ready()
    yield app, worker
    worker.stop()
    app.stop()
    forget_run(url)
    if server:
        server.stop()


def test_assimp_testmodels_corpus(served):
    assert ROOT.is_dir(), f"{ROOT} missing: run sh scripts/install-assimp-testmodels.sh (make test does)"
    app, worker = served
    mod = corpus_module()
    files = mod.corpus_files(ROOT)
    assert len(files) >= 50, len(files)  # the package holds ~130 such files
    rep = mod.run_corpus(app.url, files, ROOT, params={"max_vertices": 8}, timeout=240)
    crashed = [r for r in rep["rows"] if r["outcome"] == "crashed"]
    assert not crashed, crashed
    assert rep["files"] == len(files) == rep["accepted"] + rep["rejected"]
    assert rep["result"] >= 20 and rep["rejected"] >= 10, {k: v for k, v in rep.items() if k != "rows"}
    for r in rep["rows"]:
        if r["outcome"] == "rejected":
            assert r["http"] in (413, 415, 422) and r["reason"], r
    # A .gltf whose buffers are separate .bin files is refused with that reason, never read from disk.
    assert any("external file" in reason for reason in rep["rejected_reasons"]), rep["rejected_reasons"]
    assert worker.proc.poll() is None
    print({k: v for k, v in rep.items() if k != "rows"})
