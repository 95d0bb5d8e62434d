"""The reaper: what happens to jobs whose worker died, hung, or vanished between queue and start.

Run every ``reaper_interval`` seconds by each API process (:func:`reap_loop`) and each worker's heartbeat
thread (:func:`reap_logged`).  Any number of reapers may run at once: every decision is a compare-and-set
on the job's (status, attempt).  It works on :class:`fastmesh_jobs.store.Store`; the store knows nothing of it.
"""

from __future__ import annotations

import logging
import threading
import time

from .states import timeout_error
from .store import Store

log = logging.getLogger("fastmesh.reaper")


def reap_logged(store: Store) -> None:
    """:func:`reap` once, logging what it did to each job."""
    for job_id, action in reap(store):
        log.warning("reaper: job %s %s", job_id, action)


def reap_loop(store: Store, stop: threading.Event) -> None:
    """:func:`reap_logged` every ``reaper_interval`` seconds until ``stop`` is set."""
    while not stop.wait(store.settings.reaper_interval):
        try:
            reap_logged(store)
        except Exception as e:  # Redis down: try again next tick
            log.warning("reaper: %s", e)


def reap(store: Store) -> list[tuple[str, str]]:
    """Requeue or fail running jobs whose worker stopped heart-beating; fail overdue ones.

    Safe to run from any number of processes at once: each decision is a compare-and-set.
    Returns ``(job id, action)`` pairs, action in {"requeued", "lost", "timeout", "requeued_lost_entry"}.
    """
    actions = []
    s = store.settings
    for raw in store.redis.smembers(store.k_running):
        job_id = raw.decode()
        job = store.get(job_id)
        if job is None or job["status"] != "running":  # finished since SMEMBERS (or expired): housekeeping
            store.redis.srem(store.k_running, job_id)
            continue
        attempt = int(job["attempt"])
        if store.redis.exists(store.k_hb(job_id)):
            # Alive but overdue (a hung decoder keeps its heartbeat thread going): fail it; the worker's
            # next cancel check sees the status change and stops.
            if time.time() - job["started_at"] > s.job_timeout + s.heartbeat_ttl:
                if store.finish(job_id, attempt, "failed", error=timeout_error(s.job_timeout)):
                    actions.append((job_id, "timeout"))
            continue
        if attempt < s.max_attempts:
            if store.requeue(job_id, attempt):
                store.count_job("retried")
                actions.append((job_id, "requeued"))
        else:
            err = {"code": "worker_lost",
                   "message": f"the worker running this job stopped responding (killed or crashed) "
                              f"on each of {attempt} attempt(s); giving up"}
            if store.finish(job_id, attempt, "failed", error=err):
                actions.append((job_id, "lost"))
    actions += _reap_queued(store)
    return actions


def _reap_queued(store: Store) -> list[tuple[str, str]]:
    """Requeue queued jobs whose RQ entry vanished without the job starting.

    A worker killed between taking a job off the queue and starting it (a few milliseconds) would
    otherwise leave it "queued" forever.  A live worker passes through that gap too, so an entry
    is only declared lost when it has been missing on two looks ``heartbeat_ttl`` apart.
    """
    actions = []
    now = time.time()
    k_suspects = f"{store.prefix}:suspects"
    suspects = {k.decode(): float(v) for k, v in store.redis.hgetall(k_suspects).items()}
    for raw in store.redis.zrangebyscore(store.k_queued, "-inf", now - store.settings.heartbeat_ttl):
        job_id = raw.decode()
        job = store.get(job_id)
        if job is None or job["status"] != "queued":
            store.redis.zrem(store.k_queued, job_id)
            continue
        if job.get("rq_id") and store.redis.lpos(store.queue.key, job["rq_id"]) is not None:
            suspects.pop(job_id, None)
            continue  # still waiting its turn
        first_seen = suspects.pop(job_id, None)
        if first_seen is None:
            store.redis.hset(k_suspects, job_id, now)
            continue
        if now - first_seen < store.settings.heartbeat_ttl:
            continue
        store.redis.hdel(k_suspects, job_id)
        attempt = int(job["attempt"])
        if store.transition(job_id, "queued", {"attempt": attempt + 1}, attempt=attempt):
            store.enqueue(job_id, attempt + 1)
            actions.append((job_id, "requeued_lost_entry"))
    if suspects:  # they started (or went) in the meantime: not lost after all
        store.redis.hdel(k_suspects, *suspects)
    return actions
