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

    from service.processes import local_redis

    url, server = local_redis(DB)
    yield url
    forget_run(url)
    if server:
        server.stop()


# Modules that talk to Redis (through ``redis_url``, a stack of their own, or `make run`): marked ``redis``, so
# ``pytest -m "not redis and not browser"`` runs the method suite alone (README, Tests).
REDIS_MODULES = {"test_assimp_corpus", "test_bad_inputs", "test_faults", "test_loadtest", "test_preview",
                 "test_same_result", "test_service_api", "test_service_attacks", "test_service_client",
                 "test_service_run", "test_web", "test_web_browser", "test_worker", "test_worker_batch"}


def pytest_collection_modifyitems(config, items):
    for item in items:
        module = item.module.__name__.rpartition(".")[2]
        if module in REDIS_MODULES or "redis_url" in item.fixturenames:
            item.add_marker(pytest.mark.redis)
        if "browser" in item.fixturenames:
            item.add_marker(pytest.mark.browser)
