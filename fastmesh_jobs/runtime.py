"""What the worker processes and the service's supervisor agree on at run time: the exit status of a worker that
met a GPU error, and the polling wait both use for Redis and for each other."""

from __future__ import annotations

import time
from collections.abc import Callable

# ``fastmesh-worker``'s exit status after a job met a GPU error (``worker.jobs.is_device_error``): the job was
# failed or requeued, and the process left because its CUDA context is unusable.  A supervisor restarts it.
WORKER_EXIT_DEVICE_ERROR = 3


def wait_for(pred: Callable[[], object], timeout: float = 20.0, interval: float = 0.05, what: str = "condition"):
    """Poll ``pred`` until it returns something truthy; return that.  TimeoutError names ``what``."""
    deadline = time.monotonic() + timeout
    while True:
        value = pred()
        if value:
            return value
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(interval)
