"""The service's parts, started from Python: ``redis-server``, ``fastmesh-worker`` and the API.

Used by ``make run`` (:mod:`service.run`), the tests and the benchmarks.  The API runs as a uvicorn
subprocess (:class:`ApiProcess`, as in production: it can be killed and started again) or served in a
thread of the calling process (:class:`ServedApp`: several differently configured apps start in
milliseconds, and the app object stays at hand).
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
from collections.abc import Callable
from pathlib import Path

import httpx
import redis

from fastmesh_jobs.runtime import wait_for
from fastmesh_jobs.settings import Settings


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


PR_SET_PDEATHSIG = 1  # linux/prctl.h


def die_with_parent() -> Callable[[], None] | None:
    """A ``preexec_fn`` that makes the child receive SIGTERM when its parent dies (Linux's ``PR_SET_PDEATHSIG``),
    or None where there is no ``prctl``.

    Our children run in sessions of their own, so a signal to the parent's process group does not reach them:
    without this a parent killed outright (SIGKILL, a crash, a supervisor's last resort) would leave Redis,
    the worker and the API running.  Linux sends the signal when the *thread* that started the child ends:
    start children from a thread that lives as long as they should (the main thread).
    """
    if not sys.platform.startswith("linux"):
        return None
    try:
        import ctypes

        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None
    prctl.argtypes = [ctypes.c_int, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong]
    parent, term = os.getpid(), int(signal.SIGTERM)

    def preexec() -> None:  # runs in the forked child: nothing here may import or take a lock
        prctl(PR_SET_PDEATHSIG, term, 0, 0, 0)
        if os.getppid() != parent:  # the parent died before the request took effect
            os.kill(os.getpid(), term)

    return preexec


class RedisServer:
    """A throw-away ``redis-server`` (no persistence unless ``appendonly``), stopped by :meth:`stop`.

    ``maxmemory`` (e.g. "1gb") caps its memory with the ``noeviction`` policy: when full, writes fail
    (submissions get 503) and nothing is evicted, since any other policy could drop a queued job.
    """

    def __init__(self, port: int | None = None, appendonly: bool = False, directory: str | None = None,
                 maxmemory: str | None = None):
        exe = shutil.which("redis-server")
        if exe is None:
            raise RuntimeError("redis-server is not installed; install it with: apt-get install redis-server")
        self.port = port or free_port()
        self.dir = directory or tempfile.mkdtemp(prefix="fastmesh-redis-")
        self.appendonly = appendonly
        self.maxmemory = maxmemory
        self.exe = exe
        self.proc: subprocess.Popen | None = None
        self.start()

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def start(self) -> None:
        args = [self.exe, "--port", str(self.port), "--bind", "127.0.0.1", "--dir", self.dir, "--save", "",
                "--appendonly", "yes" if self.appendonly else "no"]
        if self.maxmemory:
            args += ["--maxmemory", self.maxmemory, "--maxmemory-policy", "noeviction"]
        self.proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                     start_new_session=True, preexec_fn=die_with_parent())
        client = redis.Redis(port=self.port)

        def up():
            if self.proc.poll() is not None:
                raise RuntimeError(f"redis-server exited with code {self.proc.returncode}")
            try:
                return client.ping()
            except redis.ConnectionError:
                return False

        wait_for(up, 10, what=f"redis-server on port {self.port}")

    def stop(self) -> None:
        if self.proc and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def local_redis(db: int) -> tuple[str, RedisServer | None]:
    """``(url, own server or None)``: database ``db`` of 127.0.0.1:6379 if it answers, else a new server."""
    try:
        redis.Redis(host="127.0.0.1", port=6379, socket_connect_timeout=1).ping()
        return f"redis://127.0.0.1:6379/{db}", None
    except redis.RedisError:
        server = RedisServer()
        return server.url.rsplit("/", 1)[0] + f"/{db}", server


def worker_command() -> list[str]:
    """The installed ``fastmesh-worker`` script next to this interpreter (a real console-script process)."""
    exe = Path(sys.executable).with_name("fastmesh-worker")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "worker.main"]


def env_value(value) -> str:
    """How a setting's value is written as the ``FASTMESH_*`` variable that reads back the same: a secret (any
    pydantic secret type: ``SecretStr``, ``SecretBytes``, ``Secret[...]``) as its real value, since ``str()`` of
    one is its mask; a list joined with commas (the ``CommaList`` fields)."""
    if hasattr(value, "get_secret_value"):
        value = value.get_secret_value()
        return value.decode() if isinstance(value, bytes) else str(value)
    if isinstance(value, list | tuple):
        return ",".join(env_value(v) for v in value)
    return str(value)


def settings_env(settings: Settings, **extra: str) -> dict[str, str]:
    """The environment that makes a subprocess read the same settings, secrets included (:func:`env_value`)."""
    env = dict(os.environ)
    for name, value in settings.model_dump().items():
        key = f"FASTMESH_{name.upper()}"
        if value is None:
            env.pop(key, None)
        else:
            env[key] = env_value(value)
    env.setdefault("OMP_NUM_THREADS", "1")
    env.update(extra)
    return env


class WorkerProcess:
    """A ``fastmesh-worker`` subprocess; :meth:`wait_ready` returns once it heart-beats in Redis."""

    def __init__(self, settings: Settings, name: str, log_path: str | os.PathLike | None = None,
                 args: tuple[str, ...] = (), **env: str):
        """``log_path`` "-" keeps the worker's output on this terminal; None logs to a temporary file."""
        self.settings, self.name = settings, name
        self.log_path = None if log_path == "-" else Path(
            log_path or tempfile.mkstemp(prefix=f"{name}-", suffix=".log")[1])
        self._log = open(self.log_path, "wb") if self.log_path else None
        # Own session: a Ctrl-C meant for the parent does not reach the worker; the parent stops it in order.
        self.proc = subprocess.Popen([*worker_command(), "--name", name, *args], env=settings_env(settings, **env),
                                     stdout=self._log, stderr=subprocess.STDOUT if self._log else None,
                                     start_new_session=True, preexec_fn=die_with_parent())

    @property
    def pid(self) -> int:
        return self.proc.pid

    def log(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path else ""

    def wait_ready(self, timeout: float = 60.0) -> WorkerProcess:
        client = redis.Redis.from_url(self.settings.redis_url)
        key = f"{self.settings.redis_prefix}:workers"

        def ready():
            if self.proc.poll() is not None:
                raise RuntimeError(f"worker {self.name} exited ({self.proc.returncode}):\n{self.log()[-3000:]}")
            return client.zscore(key, self.name) is not None

        wait_for(ready, timeout, what=f"worker {self.name}")
        return self

    def stop(self, timeout: float = 10.0) -> int | None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if self._log:
            self._log.close()
        return self.proc.returncode


class ApiProcess:
    """The API as production serves it (``uvicorn service.app:create_app --factory``, with the HTTP protocol
    :class:`service.http.Protocol`) in a subprocess reading ``settings``; :meth:`wait_ready` returns once
    it answers.  It can be killed and started again on the same port, where clients expect it."""

    def __init__(self, settings: Settings, host: str = "127.0.0.1", port: int | None = None,
                 log_path: str | os.PathLike | None = None, args: tuple[str, ...] = ("--log-level", "warning")):
        """``log_path`` "-" keeps the API's output on this terminal; None logs to a temporary file.  ``args``
        go to uvicorn."""
        self.settings, self.host, self.port, self.args = settings, host, port or free_port(), args
        self.url = f"http://{host}:{self.port}"
        self.log_path = None if log_path == "-" else Path(
            log_path or tempfile.mkstemp(prefix="fastmesh-api-", suffix=".log")[1])
        self.proc: subprocess.Popen | None = None
        self.start()

    @property
    def pid(self) -> int:
        return self.proc.pid

    def start(self) -> ApiProcess:
        """Start the process; its output is appended to the log, so a restart keeps the earlier lines."""
        log = open(self.log_path, "ab") if self.log_path else None
        # Own session: a Ctrl-C meant for the parent does not reach the API; the parent stops it in order.
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "uvicorn", "service.app:create_app", "--factory", "--host", self.host,
             "--port", str(self.port), "--http", "service.http:Protocol", *self.args],
            env=settings_env(self.settings), stdout=log, stderr=subprocess.STDOUT if log else None,
            start_new_session=True, preexec_fn=die_with_parent())
        if log:
            log.close()  # the child holds its own descriptor
        return self

    def answers(self, path: str = "/healthz") -> bool:
        """Whether ``path`` answers 200 now; RuntimeError (with the log's end) once the process has exited."""
        if self.proc.poll() is not None:
            where = f":\n{self.log()[-3000:]}" if self.log_path else " (its messages are above)"
            raise RuntimeError(f"the API exited with code {self.proc.returncode}{where}")
        try:
            return httpx.get(f"{self.url}{path}", timeout=2).status_code == 200
        except httpx.HTTPError:
            return False

    def wait_ready(self, timeout: float = 60.0) -> ApiProcess:
        wait_for(self.answers, timeout, 0.1, what=f"the API on port {self.port}")
        return self

    def log(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path else ""

    def kill(self) -> None:
        if self.proc and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()

    def stop(self, timeout: float = 10.0) -> int | None:
        if self.proc and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.kill()
        return self.proc.returncode if self.proc else None


class ServedApp:
    """``create_app(settings)`` served by uvicorn in a background thread of this process, on a free port."""

    def __init__(self, settings: Settings):
        import uvicorn  # the workers import this module too, and need neither uvicorn nor the app

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
