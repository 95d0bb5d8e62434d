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


@pytest.fixture(scope="module")
def redis_url():
    """The test Redis (127.0.0.1:6379, or one started on a free port); only this run's keys are deleted after.

    Modules that need an empty database define their own ``redis_url`` that flushes it.
    """
    from stack import DB, forget_run

    from service.testing import redis_for_tests

    url, server = redis_for_tests(DB)
    yield url
    forget_run(url)
    if server:
        server.stop()
