"""Fixtures shared across test modules."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def weights(tmp_path_factory) -> str:
    """A folder with tiny randomly initialised networks (``Pipeline.random``), for workers and the CLI."""
    from fastmesh.pipeline import Pipeline

    d = tmp_path_factory.mktemp("weights")
    Pipeline.random("tiny", seed=0).save(str(d))
    return str(d)
