"""The registry of workers: who heartbeats, what each loaded, and the vertex limit of their models.

Keys (``P`` is ``Settings.redis_prefix``)::

    P:workers               zset worker name -> last heartbeat (unix seconds)
    P:worker:<name>         hash: pid host loads jobs weights started_at (JSON-encoded values)
    P:vertex_limit          max_vertices of the model the last heartbeating worker loaded

A worker's beat is its process's; the heartbeat of the job it runs (``P:hb:<id>``) is ``states``'.
"""

from __future__ import annotations

import json
import math
import time

from .part import StorePart


class WorkerRegistry(StorePart):
    """Worker heartbeats and registrations."""

    @property
    def k_workers(self) -> str:
        return f"{self.prefix}:workers"

    def k_worker(self, name: str) -> str:
        return f"{self.prefix}:worker:{name}"

    def worker_beat(self, name: str, info: dict | None = None) -> None:
        ttl = int(math.ceil(max(self.settings.heartbeat_ttl * 3, 60)))
        with self.redis.pipeline() as pipe:
            pipe.zadd(self.k_workers, {name: time.time()})
            if info:
                pipe.hset(self.k_worker(name), mapping={k: json.dumps(v) for k, v in info.items()})
            pipe.expire(self.k_worker(name), ttl)
            if info and isinstance(info.get("max_vertices"), int):  # outlives the worker: see vertex_limit
                pipe.set(f"{self.prefix}:vertex_limit", info["max_vertices"], ex=self.settings.retention_seconds)
            # Forget workers silent for long (their own hash has expired by then too).
            pipe.zremrangebyscore(self.k_workers, "-inf", time.time() - ttl)
            pipe.execute()

    def workers_alive(self) -> list[str]:
        cutoff = time.time() - self.settings.heartbeat_ttl
        return [w.decode() for w in self.redis.zrangebyscore(self.k_workers, cutoff, "+inf")]

    def vertex_limit(self) -> int | None:
        """The smallest ``max_vertices`` the live workers' models accept; with none alive, the limit the
        last worker reported (a job queued meanwhile waits for that model); None if no worker ever said."""
        names = self.workers_alive()
        if not names:
            last = self.redis.get(f"{self.prefix}:vertex_limit")
            return int(last) if last is not None else None
        with self.redis.pipeline() as pipe:
            for n in names:
                pipe.hget(self.k_worker(n), "max_vertices")
            limits = [json.loads(v) for v in pipe.execute() if v is not None]
        limits = [v for v in limits if isinstance(v, int)]
        return min(limits) if limits else None

    def worker_last_beat(self, name: str) -> float | None:
        """Unix time of the last heartbeat of the worker ``name`` (None: none on record)."""
        return self.redis.zscore(self.k_workers, name)

    def worker_gone(self, name: str) -> None:
        self.redis.zrem(self.k_workers, name)

    def worker_info(self, name: str) -> dict:
        return {k.decode(): json.loads(v) for k, v in self.redis.hgetall(self.k_worker(name)).items()}
