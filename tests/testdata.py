"""Where the tests find real meshes: the small copy committed under tests/data, and the full corpus when present.

``tests/data/corpus`` (16 files, licences in its README) has the corpus's layout and a manifest, so every test
that needs artist meshes runs from a plain clone.  The full corpus (``../shared/corpus`` beside the repository)
only adds the checks that are corpus-scale by nature; they skip with this reason when it is absent.
"""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

TEST_CORPUS = Path(__file__).resolve().parent / "data" / "corpus"
SHARED_CORPUS = Path(__file__).resolve().parents[2] / "shared" / "corpus"
NO_SHARED_CORPUS = f"corpus-scale check: the full corpus is not at {SHARED_CORPUS}"


def manifest(root: Path = TEST_CORPUS) -> list[dict]:
    """The rows of ``root/manifest.csv`` (file, package, licence, vertices, group, kind, ...)."""
    with open(root / "manifest.csv", newline="") as fh:
        return list(csv.DictReader(fh))


def committed_meshes() -> list[Path]:
    """The committed base meshes (no poses), sorted by name."""
    return sorted(TEST_CORPUS / r["file"] for r in manifest() if r["kind"] == "mesh")


def shared_corpus_sample(k: int) -> list:
    """``k`` files spread over the full corpus, or one skipped parameter saying why there are none."""
    files = sorted(SHARED_CORPUS.glob("*/*.ply"))
    if not files:
        return [pytest.param(None, marks=pytest.mark.skip(reason=NO_SHARED_CORPUS), id="full-corpus")]
    return files[:: max(1, len(files) // k)][:k]

