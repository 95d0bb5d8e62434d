"""Real-process plumbing for tests and benchmarks: Redis, a served API, ``fastmesh-worker`` processes.

Nothing here is mocked: the API is served by uvicorn on a real port (in a thread of the calling
process, so several differently-configured apps start in milliseconds), workers are subprocesses
of the installed ``fastmesh-worker`` console script, Redis is the one on 127.0.0.1:6379 (a database
number of the caller's choosing) or, when none answers there, a ``redis-server`` started on a
free port.
"""

from __future__ import annotations

import threading

import redis

from .processes import RedisServer, WorkerProcess, free_port, settings_env, wait_for, worker_command
from .settings import Settings

__all__ = ["RedisServer", "ServedApp", "WorkerProcess", "free_port", "redis_for_tests", "settings_env", "wait_for",
           "worker_command"]


def redis_for_tests(db: int) -> tuple[str, RedisServer | None]:
    """``(url, own server or None)``: database ``db`` of 127.0.0.1:6379 if it answers, else a new server."""
    try:
        redis.Redis(host="127.0.0.1", port=6379, socket_connect_timeout=1).ping()
        return f"redis://127.0.0.1:6379/{db}", None
    except redis.RedisError:
        server = RedisServer()
        return server.url.rsplit("/", 1)[0] + f"/{db}", server


class ServedApp:
    """``create_app(settings)`` served by uvicorn in a background thread on a free port."""

    def __init__(self, settings: Settings):
        import uvicorn

        from .app import create_app
        from .http import Protocol

        self.settings = settings
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.app = create_app(settings)
        config = uvicorn.Config(self.app, host="127.0.0.1", port=self.port, log_level="warning", lifespan="on",
                                http=Protocol)
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, name=f"uvicorn-{self.port}", daemon=True)
        self.thread.start()
        wait_for(lambda: self.server.started, 15, what="uvicorn to start")

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(10)


