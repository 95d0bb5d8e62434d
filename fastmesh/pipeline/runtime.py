"""Where and how the pipeline runs: its device, torch's thread counts, each stage's timing and cancellation."""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import numpy as np
import torch

from ..faces.filtering import Predictor
from ..models.generate import Cancelled
from ..request import StageTimes

# torch CPU threads when neither the caller nor $FASTMESH_TORCH_THREADS says: decoding one sequence is a chain of
# small matrix-vector products, and on our 2-core machine a second thread made generation slower, not faster.
CPU_THREADS = 1
# Threads of the stages that run with fewer than the pipeline's own count (``Pipeline.threads``): the vertex
# decoder's step is too small to share (on 16 cores, 16 threads made the vertex stage 5x slower than 1), while
# the cell network and the face stage read thousands of points at once.  benchmarks/threads.py times each stage.
STAGE_THREADS = {"vertices": 1}


def choose_threads(device: torch.device, threads: int | None = None) -> int | None:
    """torch's thread count for generation: ``threads``, else ``$FASTMESH_TORCH_THREADS``, else
    :data:`CPU_THREADS` on a CPU device; None (torch's default) on a GPU."""
    if threads is None:
        env = os.environ.get("FASTMESH_TORCH_THREADS", "").strip()
        if env:
            try:
                threads = int(env)
            except ValueError:
                raise ValueError(f"FASTMESH_TORCH_THREADS must be a whole number, got {env!r}") from None
    if threads is None and device.type == "cpu":
        threads = CPU_THREADS
    if threads is not None and threads < 1:
        raise ValueError(f"torch threads must be at least 1, got {threads}")
    return threads


def auto_device(device: str | None = None) -> torch.device:
    if device:
        return torch.device(device)
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")



@contextmanager
def stage(name: str, timings: dict[str, float]) -> Iterator[None]:
    """Count the block in stage ``name`` of ``timings`` (seconds add up over candidates and frames): a
    :class:`StageTimes` moves its clock there and back; a plain dict gets the block's seconds added."""
    if isinstance(timings, StageTimes):
        before = timings.enter(name)
        try:
            yield
        finally:
            timings.enter(before)
        return
    t = time.perf_counter()
    try:
        yield
    finally:
        timings[name] += time.perf_counter() - t




def check(should_cancel: Callable[[], bool] | None) -> None:
    """Raise :class:`Cancelled` when ``should_cancel`` says so."""
    if should_cancel is not None and should_cancel():
        raise Cancelled("generation cancelled")


def timed_passes(predict: Predictor, timings: dict[str, float], report: Callable[[float], None], should_cancel,
           n_passes: int) -> Predictor:
    """``predict`` timed as the stages count it: its first (unmasked) pass is the face stage, each masked
    re-prediction is filtering, whose progress (the share of its passes done) it reports; cancellation is
    checked before each pass."""
    calls = 0

    def timed(order: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
        nonlocal calls
        check(should_cancel)
        with stage("faces" if calls == 0 else "filtering", timings):
            out = predict(order, mask)
        calls += 1
        if calls > 1:
            report((calls - 1) / max(1, n_passes - 1))
        return out

    return timed
