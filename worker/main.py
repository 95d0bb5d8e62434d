"""``fastmesh-worker``: an RQ worker that loads the pipeline once and runs FastMesh jobs.

It runs jobs in its own process (RQ's SimpleWorker: RQ 3's default worker starts a fresh
interpreter per job, which would reload the model every time).  A heartbeat thread keeps the
worker and its running jobs visibly alive in Redis and runs the reaper, which requeues or fails
the jobs of workers that died (SIGKILL, OOM, lost machine).

After a job meets a GPU error (a device-side assert, an illegal memory access: ``worker.jobs``), the
process's CUDA context fails every later job, so the worker records that job's outcome and exits with
status ``WORKER_EXIT_DEVICE_ERROR`` (3) instead of taking another.  Run it under a supervisor that
restarts it (``make run``, the compose file's ``restart`` policy, systemd's ``Restart=always``: README).

With ``FASTMESH_MAX_BATCH`` > 1 (unset: 8 on a GPU, 1 on a CPU) it runs that many jobs at once instead, their
vertex decoding batched (``worker.batch``), with the same job life.

Configuration: the ``FASTMESH_*`` environment (see ``fastmesh_jobs.settings.Settings``).
"""

from __future__ import annotations

import argparse
import inspect
import logging
import sys
import threading
import time

import redis
from rq import SimpleWorker
from rq.exceptions import StopRequested

from fastmesh_jobs.reaper import reap_logged
from fastmesh_jobs.runtime import WORKER_EXIT_DEVICE_ERROR
from fastmesh_jobs.settings import Settings
from fastmesh_jobs.store import Store

from .batch import BatchWorker
from .jobs import STATE

log = logging.getLogger("fastmesh.worker")
# Jobs a GPU worker runs at once unless FASTMESH_MAX_BATCH says: a decode step on a GPU costs its kernel launches,
# nearly the same for 16 rows as for 2.  On a CPU a step's cost grows with its rows (docs/results.md), so 1.
GPU_BATCH = 8


class FastMeshWorker(SimpleWorker):
    """SimpleWorker whose warm shutdown also stops the running job at its next cancel check
    (the job goes back to the queue), instead of waiting minutes for it to finish."""

    def handle_warm_shutdown_request(self):
        STATE.shutting_down = True
        super().handle_warm_shutdown_request()

    def execute_job(self, job, queue):
        """Run one job; after a GPU error in it, take no other (the work loop ends on StopRequested)."""
        super().execute_job(job, queue)
        if STATE.device_failed:
            self.log.error("Worker %s: a GPU error left this process's CUDA context unusable; exiting with "
                           "status %d for a clean restart", self.name, WORKER_EXIT_DEVICE_ERROR)
            raise StopRequested()

    def unsubscribe(self):
        """RQ's unsubscribe, with its listener told to stop before it is woken, and waited for at most 1 s.

        RQ unsubscribes, then stops its listener thread, and redis-py 8.2's stop waits for the thread with no
        limit.  A listener that takes the unsubscribe reply before it is told to stop waits for a subscription
        (RQ's 60 s) before it looks again, and the worker's exit waits with it.  Told first, the thread ends on the
        reply; it is a daemon, so a worker never waits for it longer than the join's second."""
        thread = self.pubsub_thread
        if thread is None:
            return
        self.log.info("Worker %s: unsubscribing from channel %s", self.name, self.pubsub_channel_name)
        # redis-py before 8.2: stop() only clears the thread's flag (no timeout).
        thread.stop(**({"timeout": 0} if "timeout" in inspect.signature(thread.stop).parameters else {}))
        self.pubsub.unsubscribe()
        thread.join(timeout=1)  # the thread closes its connection as it ends


def _heartbeat(store: Store, stop: threading.Event) -> None:
    s = store.settings
    last_reap = 0.0
    while True:
        try:
            store.worker_beat(STATE.name, STATE.info())
            for job_id, attempt in list(STATE.running.items()):
                store.heartbeat(job_id, attempt)
            if time.monotonic() - last_reap >= s.reaper_interval:
                last_reap = time.monotonic()
                reap_logged(store)
        except Exception as e:  # Redis away: keep trying; the job's own writes will fail loudly enough
            log.warning("heartbeat: %s", e)
        if stop.wait(s.heartbeat_interval):
            return


class NameTaken(RuntimeError):
    """A live worker heart-beats under the name asked for."""


def take_name(store: Store, rq_conn: redis.Redis, name: str) -> None:
    """Make ``name`` this process's, as a restarted worker (systemd, compose, Kubernetes) needs.

    A registration whose heartbeat has stopped is stale: a worker killed moments ago (kill -9, OOM)
    left a recent beat, so this waits until the beat is ``heartbeat_ttl`` old while watching that it
    does not move; a beat that moves is a live worker (:class:`NameTaken`).  Then RQ's record of the
    dead worker, which RQ itself would keep for minutes, is marked dead so RQ accepts the name.
    """
    s = store.settings
    last = store.worker_last_beat(name)
    while last is not None and time.time() - last < s.heartbeat_ttl:
        time.sleep(min(s.heartbeat_interval, max(0.05, last + s.heartbeat_ttl - time.time())))
        now_last = store.worker_last_beat(name)
        if now_last != last:
            raise NameTaken(f"a worker named {name!r} is alive (its heartbeat moved); give this one another --name")
    stale = FastMeshWorker.find_by_key(FastMeshWorker.redis_worker_namespace_prefix + name, connection=rq_conn)
    if stale is not None and stale.death_date is None:
        log.warning("worker name %s: clearing the registration of a dead worker (no heartbeat for %.0f s)",
                    name, time.time() - last if last else float("nan"))
        stale.register_death()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="fastmesh-worker", description=__doc__.split("\n\n")[0])
    parser.add_argument("--burst", action="store_true", help="exit when the queue is empty")
    parser.add_argument("--max-jobs", type=int, default=None, help="exit after this many jobs")
    parser.add_argument("--name", default=None, help="worker name (default fastmesh-<host>-<pid>)")
    parser.add_argument("--log-level", default="INFO")
    args = parser.parse_args(argv)
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    try:
        settings = Settings()
    except Exception as e:
        print(f"fastmesh-worker: bad configuration: {e}", file=sys.stderr)
        return 2
    if args.name:
        STATE.name = args.name
    store = Store(settings)
    try:
        store.redis.ping()
    except redis.RedisError as e:
        print(f"fastmesh-worker: cannot reach Redis at {settings.redis_url}: {e}", file=sys.stderr)
        return 1
    STATE.configure(settings, store)
    # RQ tunes the socket timeout of the connection it is given for its long BLMOVE: give it its own.
    rq_conn = redis.Redis.from_url(settings.redis_url)
    try:
        take_name(store, rq_conn, STATE.name)
    except NameTaken as e:
        print(f"fastmesh-worker: {e}", file=sys.stderr)
        return 1
    try:
        STATE.ensure()  # load the model now: a worker is only "alive" once it can take a job
    except (FileNotFoundError, ValueError, RuntimeError) as e:
        print(f"fastmesh-worker: cannot load the model: {e}\n(set FASTMESH_WEIGHTS to a weights folder)",
              file=sys.stderr)
        return 2
    stop = threading.Event()
    beat = threading.Thread(target=_heartbeat, args=(store, stop), name="fastmesh-heartbeat", daemon=True)
    beat.start()
    STATE.max_batch = settings.max_batch or (GPU_BATCH if STATE.pipeline.device.type == "cuda" else 1)
    log.info("worker %s ready on queue %s (%s), %d job(s) at once", STATE.name, settings.queue_name,
             settings.redis_url, STATE.max_batch)
    try:
        if STATE.max_batch > 1:
            BatchWorker(store, STATE.max_batch).work(burst=args.burst, max_jobs=args.max_jobs)
        else:
            worker = FastMeshWorker([store.queue.name], connection=rq_conn, name=STATE.name)
            worker.work(burst=args.burst, max_jobs=args.max_jobs, logging_level=args.log_level)
    finally:
        stop.set()
        try:
            store.worker_gone(STATE.name)
        except redis.RedisError:
            pass
    return WORKER_EXIT_DEVICE_ERROR if STATE.device_failed else 0


if __name__ == "__main__":
    sys.exit(main())
