"""What every part of the store stands on: one settings object, one Redis connection, the key prefix, the RQ queue.

Each concern of :class:`fastmesh_jobs.store.Store` is a class of its own module that owns its Redis keys and
methods (``states``, ``blobs``, ``workers``, ``limits``, ``idempotency``, ``telemetry``); ``Store`` is all of them
over this one :class:`StorePart`.
"""

from __future__ import annotations

import redis
from redis.commands.core import Script
from rq import Queue

from .settings import Settings


class StorePart:
    """Redis access for one settings object.  Thread-safe (redis-py pools connections)."""

    def __init__(self, settings: Settings, client: redis.Redis | None = None):
        self.settings = settings
        # Bytes in, bytes out: RQ needs raw bytes and our blobs are binary; hashes are decoded by hand.
        self.redis = client or redis.Redis.from_url(settings.redis_url, socket_connect_timeout=5, socket_keepalive=True)
        self.prefix = settings.redis_prefix
        self.queue = Queue(settings.queue_name, connection=self.redis)
        self._scripts: dict[str, Script] = {}

    def _script(self, source: str) -> Script:
        """The Lua script ``source`` registered with this connection (once: it is run by its SHA after that)."""
        script = self._scripts.get(source)
        if script is None:
            script = self._scripts[source] = self.redis.register_script(source)
        return script
