"""``make run`` (``python -m service.run``): starts Redis, a worker and the API, prints a curl example that
works as printed, and stops everything it started on Ctrl-C."""

from __future__ import annotations

import io
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import trimesh
from stack import printed

from fastmesh_jobs.runtime import wait_for
from service.processes import free_port


def children(pid: int) -> list[int]:
    out = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        out += [int(c) for c in (task / "children").read_text().split()]
    return out


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def run_env(**extra) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith("FASTMESH_")}
    env.update(OMP_NUM_THREADS="1", **extra)
    return env


def test_make_run_serves_the_printed_curl_example_and_stops_on_ctrl_c(weights, tmp_path):
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "service.run"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, env=run_env(FASTMESH_PORT=str(port), FASTMESH_WEIGHTS=weights))
    lines: list[str] = []
    try:
        def printed():
            line = proc.stdout.readline()
            if not line and proc.poll() is not None:
                raise RuntimeError("service.run exited:\n" + "".join(lines))
            lines.append(line)
            return "Ctrl-C stops everything" in line

        wait_for(printed, 120, 0, what="the curl example")
        text = "".join(lines)
        assert f"http://127.0.0.1:{port}" in text
        start = next(i for i, ln in enumerate(lines) if ln.startswith("JOB=$(curl"))
        example = "".join(lines[start:start + 2])
        assert lines[start + 1].startswith("curl ")
        r = subprocess.run(["bash", "-c", "set -e\n" + example], cwd=tmp_path, capture_output=True, text=True,
                           timeout=120)
        assert r.returncode == 0, r.stderr + r.stdout
        mesh = trimesh.load(io.BytesIO((tmp_path / "example.glb").read_bytes()), file_type="glb", force="mesh")
        assert len(mesh.faces) > 0
        kids = children(proc.pid)
        assert len(kids) == 3  # redis-server, fastmesh-worker, uvicorn
    finally:
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0, rest
    assert "stopping" in rest
    time.sleep(0.2)
    assert [k for k in kids if alive(k)] == []


def test_make_run_restarts_a_worker_that_dies(weights, tmp_path):
    """kill -9 of the worker (as the OOM killer does): `make run` starts it again and keeps serving."""
    import httpx

    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "service.run"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, env=run_env(FASTMESH_PORT=str(port), FASTMESH_WEIGHTS=weights,
                                                   FASTMESH_HEARTBEAT_TTL="2", FASTMESH_HEARTBEAT_INTERVAL="0.5"))
    lines: list[str] = []

    try:
        wait_for(printed(proc, lines, "Ctrl-C stops everything"), 120, 0, what="the service to be ready")
        worker = next(k for k in children(proc.pid) if "fastmesh-worker" in Path(f"/proc/{k}/cmdline").read_text()
                      or "worker.main" in Path(f"/proc/{k}/cmdline").read_text())
        os.kill(worker, signal.SIGKILL)
        wait_for(printed(proc, lines, "starting it again"), 30, 0, what="the restart message")
        url = f"http://127.0.0.1:{port}"
        points = "".join(f"{x:.4f} {y:.4f} {z:.4f}\n" for x, y, z in trimesh.creation.icosphere(2).vertices)
        job = httpx.post(f"{url}/v1/jobs", files={"file": ("ball.xyz", points)}, data={"max_vertices": "16"},
                         timeout=30).json()
        result = httpx.get(f"{url}/v1/jobs/{job['id']}/result", params={"wait": 120}, timeout=150)
        assert result.status_code == 200, result.text  # the new worker ran it
        assert proc.poll() is None and worker not in children(proc.pid)
        assert len(children(proc.pid)) == 3
    finally:
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0, "".join(lines) + rest


def test_make_run_without_redis_says_what_to_install(tmp_path):
    r = subprocess.run([sys.executable, "-m", "service.run"], capture_output=True, text=True, timeout=60,
                       env=run_env(PATH=str(tmp_path), FASTMESH_PORT=str(free_port())))
    assert r.returncode == 1
    assert "apt-get install redis-server" in r.stdout


def test_make_run_with_unreachable_redis_url(tmp_path):
    url = f"redis://127.0.0.1:{free_port()}/0"
    r = subprocess.run([sys.executable, "-m", "service.run"], capture_output=True, text=True, timeout=60,
                       env=run_env(FASTMESH_REDIS_URL=url, FASTMESH_PORT=str(free_port())))
    assert r.returncode == 1 and "cannot reach Redis" in r.stdout


def test_make_run_stops_on_ctrl_c_even_when_started_with_sigint_ignored(weights):
    """A parent that ignores SIGINT (some launchers, and this test suite after some modules) passes that on:
    `make run` must still stop on Ctrl-C, not wait forever."""
    proc = subprocess.Popen([sys.executable, "-m", "service.run"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, env=run_env(FASTMESH_PORT=str(free_port()), FASTMESH_WEIGHTS=weights),
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    try:
        def printed():
            line = proc.stdout.readline()
            if not line and proc.poll() is not None:
                raise RuntimeError("service.run exited")
            return "Ctrl-C stops everything" in line

        wait_for(printed, 120, 0, what="the service to be ready")
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            rest, _ = proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
            raise
    assert proc.returncode == 0 and "stopping" in rest


def _started(weights) -> tuple[subprocess.Popen, list[int], list[str]]:
    """`make run` on a free port, ready, with its three children (redis-server, the worker, uvicorn)."""
    proc = subprocess.Popen([sys.executable, "-m", "service.run"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, env=run_env(FASTMESH_PORT=str(free_port()), FASTMESH_WEIGHTS=weights))
    lines: list[str] = []
    try:
        wait_for(printed(proc, lines, "Ctrl-C stops everything"), 120, 0, what="the service to be ready")
    except BaseException:
        proc.kill()
        raise
    kids = children(proc.pid)
    assert len(kids) == 3, kids
    return proc, kids, lines


def _gone(kids: list[int], timeout: float = 20.0) -> list[int]:
    """The children still alive after ``timeout`` s (killed, so that a failing test leaves none behind)."""
    try:
        wait_for(lambda: not any(alive(k) for k in kids), timeout, 0.1, what="the children to exit")
    except TimeoutError:
        pass
    left = [k for k in kids if alive(k)]
    for k in left:
        os.kill(k, signal.SIGKILL)
    return left


def test_a_second_sigterm_while_stopping_changes_nothing(weights):
    """A supervisor that sends TERM twice: the first shutdown runs to its end, and no child outlives it."""
    proc, kids, lines = _started(weights)
    try:
        proc.send_signal(signal.SIGTERM)
        time.sleep(0.3)  # inside the shutdown: the API or the worker is being stopped
        proc.send_signal(signal.SIGTERM)
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=60)
    finally:
        left = _gone(kids)
        if proc.poll() is None:
            proc.kill()
    assert left == [], f"children left running: {left}"
    assert proc.returncode == 0 and "Traceback" not in rest and "KeyboardInterrupt" not in rest, rest
    assert "stopping ..." in rest and "already stopping" in rest


def test_children_end_with_a_parent_that_is_killed(weights):
    """kill -9 of `make run` (no shutdown at all): Redis, the worker and the API still go."""
    proc, kids, _ = _started(weights)
    proc.kill()
    proc.wait(10)
    left = _gone(kids)  # they hold its stdout: read it only once they are gone
    proc.communicate(timeout=10)
    assert left == [], f"children left running: {left}"
