"""Training batches made by worker processes, ahead of the step that needs them.

On a GPU the step takes milliseconds and ``task.make_batch`` (augmenting, quantising and sampling
meshes; the cell task's features) takes far longer on one CPU core, so the accelerator waits.
``BatchMaker`` hands the batches of an epoch to ``workers`` forked processes, a bounded window
ahead, and yields them in order.  Each batch draws its random numbers from the same seed
``(seed, epoch, position, rank)`` as in-process, so a run with workers sees exactly the batches
of a run without them (tested).
"""

from __future__ import annotations

import multiprocessing as mp
from collections import deque
from collections.abc import Iterator

import numpy as np
import torch

from .data import one_thread

AHEAD = 3  # batches in flight per worker: enough to hide the variance of batch cost, bounded in memory

_STATE: dict = {}  # what a forked worker makes batches from (inherited, never pickled)


def _make(task, ds, cfg, batch: np.ndarray, seed: list[int], train: bool) -> dict:
    rng = np.random.default_rng(seed)
    return task.make_batch(ds, batch, rng, cfg, train=train)


def _worker_make(batch: np.ndarray, seed: list[int]) -> dict:
    out = _make(_STATE["task"], _STATE["ds"], _STATE["cfg"], batch, seed, True)
    # numpy crosses the pipe as plain bytes; torch tensors would travel as shared-memory handles, one
    # file descriptor each, which a deep window of batches can run out of.
    return {k: v.numpy() for k, v in out.items()}


class BatchMaker:
    """Training batches of ``task`` from ``ds``, made in-process (``workers`` 0) or by a process pool.

    Use as a context manager; ``epoch(batches, epoch, start, rank)`` yields the batches of one
    epoch from position ``start`` on, as dicts of CPU tensors.
    """

    def __init__(self, task, ds, cfg, workers: int = 0):
        self.task, self.ds, self.cfg, self.workers = task, ds, cfg, workers
        self.pool = None

    def __enter__(self) -> BatchMaker:
        if self.workers > 0:
            _STATE.update(task=self.task, ds=self.ds, cfg=self.cfg)
            # fork: the workers share the dataset's arrays with this process instead of copying them.
            self.pool = mp.get_context("fork").Pool(self.workers, initializer=one_thread)
        return self

    def __exit__(self, *exc) -> None:
        if self.pool is not None:
            self.pool.terminate()
            self.pool.join()
            self.pool = None
        _STATE.clear()

    def epoch(self, batches: list[np.ndarray], epoch: int, start: int, rank: int) -> Iterator[dict]:
        seed = self.cfg.seed
        if self.pool is None:
            for pos in range(start, len(batches)):
                yield _make(self.task, self.ds, self.cfg, batches[pos], [seed, epoch, pos, rank], True)
            return
        window = deque()
        nxt = start
        while nxt < len(batches) or window:
            while nxt < len(batches) and len(window) < AHEAD * self.workers:
                window.append(self.pool.apply_async(_worker_make, (batches[nxt], [seed, epoch, nxt, rank])))
                nxt += 1
            yield {k: torch.from_numpy(v) for k, v in window.popleft().get().items()}
