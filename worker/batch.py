"""``fastmesh-worker`` with ``FASTMESH_MAX_BATCH`` > 1: up to that many jobs at once, their vertex decoding
batched (:class:`fastmesh.batch.Batch`).

Continuous batching at the decoder's rounds: whenever a job ends, the next queued one is started and joins the
next decode round, so the batch stays full while jobs wait.  Jobs are taken off RQ's queue by this loop itself
(each entry names a job id and attempt: ``fastmesh_jobs.store.Store.enqueue``), not by RQ's SimpleWorker, which runs one
job at a time; its entry is then deleted, as RQ does with a finished job (``result_ttl=0``).

Each job's life is the one-at-a-time worker's (``worker.jobs``): started by the same compare-and-set, beaten by
the same heartbeat thread (``STATE.running``), cancelled, timed out, handed back on a warm shutdown (SIGTERM:
every running job goes back to the queue at its next cancel check, then the worker exits) and recorded by the
same code.  A worker killed mid-batch loses no job: the reaper requeues every job whose heartbeat lapses, and
one taken off the queue but not yet started (``_reap_queued``).  After a GPU error the jobs of the decoding
that met it are each given to another worker once (``worker.jobs._device_failure``; a job that met one before
decodes in no batch but its own), the other running jobs are handed back, and the worker exits with status 3.
"""

from __future__ import annotations

import logging
import signal

import redis
from rq.exceptions import NoSuchJobError
from rq.job import Job as RQJob

from fastmesh.batch import Batch
from fastmesh_jobs.runtime import WORKER_EXIT_DEVICE_ERROR, wait_for
from fastmesh_jobs.store import Store

from .jobs import (
    STATE,
    Job,
    _redis_answers,
    _release,
    conclude,
    give_back_memory,
    is_device_error,
    outcome_recorded,
    prepare,
)

log = logging.getLogger("fastmesh.worker")
POLL_SECONDS = 1  # longest wait on an empty queue while no job runs: a shutdown is seen within it


class BatchWorker:
    """Runs up to ``max_batch`` jobs of ``store``'s queue at once in this process (``STATE.pipeline``)."""

    def __init__(self, store: Store, max_batch: int):
        self.store, self.max_batch = store, max_batch
        self.jobs: dict[str, Job] = {}  # the running jobs, by id
        self.batch = Batch(STATE.pipeline, fatal=is_device_error)

    def work(self, burst: bool = False, max_jobs: int | None = None) -> None:
        """Take and run jobs until a shutdown, a GPU error, ``max_jobs`` taken, or (``burst``) an empty queue."""
        self._signals()
        taken = 0
        try:
            while True:
                dry, taken = self._fill(burst, taken, max_jobs)
                if len(self.batch):
                    self.batch.round()
                    self._settle()
                elif STATE.shutting_down or STATE.device_failed or (burst and dry) or (
                        max_jobs is not None and taken >= max_jobs):
                    break
        except BaseException:  # a cold shutdown or a crash of this loop: the running jobs go back to the queue
            self._hand_back("worker shutting down")
            raise
        if STATE.device_failed:
            log.error("Worker %s: a GPU error left this process's CUDA context unusable; exiting with status %d "
                      "for a clean restart", STATE.name, WORKER_EXIT_DEVICE_ERROR)

    def _fill(self, burst: bool, taken: int, max_jobs: int | None) -> tuple[bool, int]:
        """Start queued jobs while there is room; returns (whether the queue ran dry, jobs taken so far)."""
        while len(self.batch) < self.max_batch and not (STATE.shutting_down or STATE.device_failed) and (
                max_jobs is None or taken < max_jobs):
            entry = self._pop(wait=not len(self.batch) and not burst)
            if entry is None:
                return True, taken
            taken += 1
            self._start(*entry)
            self._settle()  # a job can end without decoding (refused, a bad input, rebuilt from its planes)
        return False, taken

    def _pop(self, wait: bool) -> tuple[str, int] | None:
        """The next queued (job id, attempt), its RQ entry deleted; None when the queue is empty (after
        ``POLL_SECONDS`` with ``wait``)."""
        conn, key = self.store.redis, self.store.queue.key
        while True:
            try:
                got = conn.blpop([key], timeout=POLL_SECONDS) if wait else conn.lpop(key)
            except (redis.ConnectionError, redis.TimeoutError) as e:
                log.warning("queue unreachable (%s); waiting for Redis", e)
                wait_for(lambda: _redis_answers(self.store), self.store.settings.redis_outage_wait, 0.5,
                         what="Redis")
                continue
            if got is None:
                return None
            rq_id = (got[1] if wait else got).decode()
            try:
                entry = RQJob.fetch(rq_id, connection=conn)
            except NoSuchJobError:  # deleted meanwhile: nothing to run
                continue
            job_id, attempt = entry.args
            entry.delete(remove_from_queue=False)
            return job_id, int(attempt)

    def _start(self, job_id: str, attempt: int) -> None:
        """Start the job (queued -> running) and run it to its first decoding, or to its end."""
        if not self.store.start(job_id, attempt, STATE.name):
            log.info("job %s attempt %d: not queued any more (cancelled or superseded), skipped", job_id, attempt)
            return
        STATE.running[job_id] = attempt
        started = False
        with outcome_recorded(self.store, job_id, attempt):
            job = prepare(self.store, job_id, attempt)
            if job is not None and job.error is not None:
                conclude(self.store, job, job.error)
            elif job is not None:
                self.jobs[job_id] = job
                started = True
                self.batch.add(job_id, STATE.pipeline.steps(job.shape, job.params, job.ctl.progress,
                                                            job.ctl.should_cancel), solo=job.device_errors > 0)
        if not started:
            self._ended(job_id)

    def _settle(self) -> None:
        """Record the jobs that ended; after a GPU error, hand back the others."""
        for job_id, outcome in self.batch.pop_done().items():
            job = self.jobs.pop(job_id)
            try:
                with outcome_recorded(self.store, job_id, job.attempt):
                    conclude(self.store, job, outcome)
            finally:
                self._ended(job_id)
        if self.batch.failed is not None:
            self.batch.close()
            self._hand_back("the GPU failed during another job of its batch")

    def _hand_back(self, reason: str) -> None:
        """Every running job back to the queue, as its next attempt."""
        self.batch.close()
        for job_id, job in list(self.jobs.items()):
            try:
                _release(self.store, job_id, job.attempt, reason)
            except redis.RedisError as e:  # the reaper requeues it once its heartbeat lapses
                log.warning("job %s: could not hand it back (%s)", job_id, e)
            self.jobs.pop(job_id)
            self._ended(job_id)

    @staticmethod
    def _ended(job_id: str) -> None:
        STATE.running.pop(job_id, None)
        STATE.jobs += 1
        if not STATE.running:
            give_back_memory()

    @staticmethod
    def _signals() -> None:
        """SIGTERM or SIGINT: a warm shutdown (the running jobs stop at their next cancel check and go back to the
        queue); a second one: a cold shutdown (SystemExit; the running jobs are handed back at once)."""

        def stop(signum, frame):
            if STATE.shutting_down:
                raise SystemExit(1)
            STATE.shutting_down = True
            log.warning("warm shutdown (signal %d): handing back the %d running job(s)", signum, len(STATE.running))

        signal.signal(signal.SIGTERM, stop)
        signal.signal(signal.SIGINT, stop)
