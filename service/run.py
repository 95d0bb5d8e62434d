"""``make run``: Redis (given or started), one worker and the API on 127.0.0.1:8000, until Ctrl-C.

    python -m service.run            # FASTMESH_PORT, FASTMESH_REDIS_URL, FASTMESH_WEIGHTS, ... apply

Prints a curl example that works as printed.  Ctrl-C (or SIGTERM) stops the API, then the worker
(a job it was running goes back to the queue), then the Redis it started; a second one while it stops
changes nothing.  Its children end with it even if it is killed outright
(:func:`service.processes.die_with_parent`).
"""

from __future__ import annotations

import os
import shlex
import shutil
import signal
import socket
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import redis

from fastmesh_jobs.runtime import WORKER_EXIT_DEVICE_ERROR, wait_for
from fastmesh_jobs.settings import Settings

from .processes import ApiProcess, RedisServer, WorkerProcess

# A worker that dies (OOM, kill -9) or leaves after a GPU error (exit status WORKER_EXIT_DEVICE_ERROR: its CUDA
# context is unusable, the job it ran is failed or requeued) is started again, after 1, 2, 4, ... s; one that
# keeps dying is a fault to show, so after MAX_RESTARTS restarts within RESTART_WINDOW seconds `make run` stops.
MAX_RESTARTS = 5
RESTART_WINDOW = 600.0
RESTART_MAX_DELAY = 30.0


def _say(msg: str) -> None:
    print(f"[fastmesh run] {msg}", flush=True)


def _port_busy(host: str, port: int) -> bool:
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
            return False
        except OSError:
            return True


def example_input(path: Path, n: int = 2000) -> Path:
    """A point cloud of a rounded box (x y z nx ny nz per line), the shape the curl example uploads."""
    rng = np.random.default_rng(0)
    p = rng.normal(size=(n, 3))
    p /= np.abs(p).max(1, keepdims=True)  # onto the cube's surface...
    p = np.sign(p) * np.abs(p) ** 0.7 * [1.0, 0.6, 0.4]  # ...rounded and stretched
    np.savetxt(path, p, fmt="%.5f")
    return path


def _curl(url: str, example: Path, key: str | None) -> str:
    auth = f"-H {shlex.quote('Authorization: Bearer ' + key)} " if key else ""
    out = example.with_suffix(".glb").name
    return (f"JOB=$(curl -sS {auth}-F file=@{shlex.quote(str(example))} {url}/v1/jobs"
            " | python3 -c 'import json,sys; print(json.load(sys.stdin)[\"id\"])')\n"
            f"curl -sS {auth}-o {out} \"{url}/v1/jobs/$JOB/result?format=glb&wait=300\" && ls -l {out}")


def _fastmesh_cli() -> str:
    exe = Path(sys.executable).with_name("fastmesh")
    if exe.exists():
        try:
            return str(exe.relative_to(Path.cwd()))
        except ValueError:
            return str(exe)
    return "fastmesh"


def _restart(worker: WorkerProcess, restarts: list[float]) -> WorkerProcess | None:
    """A new worker of the same name after ``worker`` exited, after a back-off that doubles with each
    restart in the last :data:`RESTART_WINDOW` seconds; None once :data:`MAX_RESTARTS` were spent there."""
    code = worker.proc.returncode
    worker.stop()
    now = time.monotonic()
    restarts[:] = [t for t in restarts if now - t < RESTART_WINDOW]
    if len(restarts) >= MAX_RESTARTS:
        _say(f"the worker exited with code {code}, its {len(restarts) + 1}th exit within {RESTART_WINDOW:g} s; "
             "stopping")
        return None
    delay = min(RESTART_MAX_DELAY, 2.0 ** len(restarts))
    why = " after a GPU error (a fresh process gets a fresh CUDA context)" if code == WORKER_EXIT_DEVICE_ERROR else ""
    _say(f"the worker exited with code {code}{why}; starting it again in {delay:g} s "
         f"(restart {len(restarts) + 1} of at most {MAX_RESTARTS} within {RESTART_WINDOW:g} s)")
    time.sleep(delay)
    restarts.append(time.monotonic())
    return WorkerProcess(worker.settings, worker.name, log_path="-")


class _StopOnce:
    """The SIGTERM and SIGINT handler: the first signal raises KeyboardInterrupt, a later one only says so.

    Once: a second Ctrl-C or SIGTERM (a supervisor sending TERM twice) must not break off the shutdown the first
    one began, which would leave the worker and Redis running.
    """

    def __init__(self):
        self.stopping = False

    def __call__(self, *_) -> None:
        if self.stopping:
            os.write(1, b"[fastmesh run] already stopping\n")  # print() is not safe inside a signal handler
            return
        self.stopping = True
        raise KeyboardInterrupt


@dataclass
class _Started:
    """What ``make run`` started (each None until it is), stopped by :meth:`stop` in reverse order."""

    workdir: Path
    server: RedisServer | None = None
    worker: WorkerProcess | None = None
    api: ApiProcess | None = None

    def stop(self) -> None:
        if self.api is not None:
            self.api.stop()
        if self.worker is not None:
            self.worker.stop(15)
        if self.server is not None:
            self.server.stop()
        shutil.rmtree(self.workdir, ignore_errors=True)


def _use_redis(settings: Settings, started: _Started) -> Settings | None:
    """``settings`` pointing at the Redis to use: ``FASTMESH_REDIS_URL``'s when it is set and answers, else a
    redis-server started in ``started.workdir``; None, once said why, when neither can be."""
    if "FASTMESH_REDIS_URL" in os.environ:
        try:
            redis.Redis.from_url(settings.redis_url, socket_connect_timeout=3).ping()
        except redis.RedisError as e:
            _say(f"cannot reach Redis at FASTMESH_REDIS_URL={settings.redis_url}: {e}")
            return None
        _say(f"using Redis at {settings.redis_url}")
        return settings
    if shutil.which("redis-server") is None:
        _say("redis-server is not installed. Install it with:\n\n    apt-get install redis-server\n\n"
             "or point at a running one: FASTMESH_REDIS_URL=redis://HOST:6379/0 make run")
        return None
    server = started.server = RedisServer(directory=str(started.workdir), maxmemory=settings.redis_maxmemory)
    _say(f"started redis-server on port {server.port} (at most {settings.redis_maxmemory}; data in "
         f"{started.workdir}, not kept: stopping `make run` or a restart of this Redis forgets its jobs)")
    return settings.model_copy(update={"redis_url": server.url})


def _announce(settings: Settings, url: str, workdir: Path) -> None:
    """Say where the API serves, with a curl example (and the CLI's) that upload a sample point cloud."""
    example = example_input(workdir / "example.xyz")
    key = settings.api_keys[0] if settings.api_keys else None
    print(f"\nFastMesh is serving on {url}  (API docs: {url}/docs, metrics: {url}/metrics)\n"
          f"Try it (uploads a sample point cloud, waits, downloads the mesh):\n\n"
          f"{_curl(url, example, key)}\n\n"
          f"or: {_fastmesh_cli()} submit {example} --url {url} -o example.glb"
          f"{' --api-key ' + shlex.quote(key) if key else ''}\n\nCtrl-C stops everything.\n", flush=True)


def _supervise(started: _Started) -> int:
    """Watch the API and the worker until the API exits or the worker exits once too often (status 1); a worker
    that exits is started again (:func:`_restart`)."""
    restarts: list[float] = []
    while True:
        if started.api.proc.poll() is not None:
            _say(f"the API exited with code {started.api.proc.returncode}; stopping")
            return 1
        if started.worker.proc.poll() is not None:
            started.worker = _restart(started.worker, restarts)
            if started.worker is None:
                return 1
        time.sleep(0.5)


def _serve(settings: Settings, started: _Started) -> int:
    """Start Redis (or use the given one), the worker and the API into ``started``, and supervise them."""
    settings = _use_redis(settings, started)
    if settings is None:
        return 1
    if _port_busy(settings.host, settings.port):
        _say(f"port {settings.port} on {settings.host} is in use; choose another with FASTMESH_PORT=8001 make run")
        return 1
    worker = started.worker = WorkerProcess(settings, f"fastmesh-run-{os.getpid()}", log_path="-")
    api = started.api = ApiProcess(settings, settings.host, settings.port, log_path="-", args=("--no-access-log",))
    _say("loading the model and starting the API ...")

    def ready():
        if worker.proc.poll() is not None:
            raise RuntimeError(f"the worker exited with code {worker.proc.returncode} (its messages are above)")
        return api.answers("/readyz")

    wait_for(ready, 300, 0.25, what="the worker and the API to be ready")
    _announce(settings, api.url, started.workdir)
    return _supervise(started)


def main() -> int:
    try:
        settings = Settings()
    except Exception as e:
        _say(f"bad FASTMESH_* configuration: {e}")
        return 2
    started = _Started(Path(tempfile.mkdtemp(prefix="fastmesh-run-")))
    stop = _StopOnce()
    signal.signal(signal.SIGTERM, stop)
    # Also Ctrl-C, explicitly: a process started with SIGINT ignored (a parent that ignores it, as some
    # launchers and test runners leave it) would otherwise never see KeyboardInterrupt and never stop.
    signal.signal(signal.SIGINT, stop)
    try:
        return _serve(settings, started)
    except KeyboardInterrupt:
        _say("stopping ...")
        return 0
    except (RuntimeError, TimeoutError) as e:
        _say(str(e))
        return 1
    finally:
        stop.stopping = True  # however we got here (an error, the API exiting): a signal now must not interrupt this
        started.stop()


if __name__ == "__main__":
    sys.exit(main())
