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

from service.testing import free_port, wait_for


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
