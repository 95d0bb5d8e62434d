"""Secret settings reach the service's processes unchanged: ``make run`` (``python -m service.run``) starts the
worker and the API through :func:`service.processes.settings_env`, and ``str()`` of a pydantic secret is its mask.

The first test checks every secret field of :class:`Settings` (found by type, so a secret added later is
checked too) by reading the settings back in a child process; the second goes through ``make run`` itself: a
webhook must be signed with ``FASTMESH_WEBHOOK_SECRET``, as README's verification expects.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import signal
import subprocess
import sys
import typing
from pathlib import Path

import httpx
import trimesh
from stack import printed
from test_service_run import children, run_env
from test_webhooks import Receiver

from fastmesh_jobs.runtime import wait_for
from fastmesh_jobs.settings import Settings
from service.processes import free_port, settings_env

# A child's settings, every field shown as it reads it: a secret by its real value.
READ_BACK = ("import json; from fastmesh_jobs.settings import Settings\n"
             "s = Settings()\n"
             "print(json.dumps({n: (v.get_secret_value() if hasattr(v, 'get_secret_value') else v)\n"
             "                  for n, v in ((n, getattr(s, n)) for n in Settings.model_fields)}, default=str))")


def is_secret_type(hint) -> bool:
    """Whether the annotation ``hint`` is, or holds, a pydantic secret type (``SecretStr | None`` included)."""
    if isinstance(hint, type) and hasattr(hint, "get_secret_value"):
        return True
    return any(is_secret_type(arg) for arg in typing.get_args(hint))


def secret_fields() -> list[str]:
    return [name for name, field in Settings.model_fields.items() if is_secret_type(field.annotation)]


def test_every_secret_setting_reaches_a_child_process_unchanged():
    secrets = secret_fields()
    assert "webhook_secret" in secrets  # the finder finds what is there today
    settings = Settings(**{name: f"s3cret-{name}-k=v,x" for name in secrets})
    out = subprocess.run([sys.executable, "-c", READ_BACK], env=settings_env(settings), capture_output=True,
                         text=True, timeout=60, check=True).stdout
    child = json.loads(out)
    for name in secrets:
        assert child[name] == f"s3cret-{name}-k=v,x", (name, child[name])
    # Every other setting reads back the same as well.
    mine = {n: (v.get_secret_value() if hasattr(v, "get_secret_value") else v)
            for n, v in ((n, getattr(settings, n)) for n in Settings.model_fields)}
    assert child == json.loads(json.dumps(mine, default=str))


def environ(pid: int) -> dict[str, str]:
    raw = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
    return dict(item.decode(errors="replace").split("=", 1) for item in raw if b"=" in item)


def test_make_run_signs_webhooks_with_the_configured_secret(weights):
    """``FASTMESH_WEBHOOK_SECRET=s3cret FASTMESH_WEBHOOK_ALLOW_PRIVATE=1 make run``, a receiver on 127.0.0.1:
    the delivery's signature is the HMAC keyed with s3cret, and the worker and the API both hold it."""
    port = free_port()
    receiver = Receiver()
    proc = subprocess.Popen([sys.executable, "-m", "service.run"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, env=run_env(FASTMESH_PORT=str(port), FASTMESH_WEIGHTS=weights,
                                                   FASTMESH_WEBHOOK_SECRET="s3cret",
                                                   FASTMESH_WEBHOOK_ALLOW_PRIVATE="1"))
    lines: list[str] = []
    try:
        wait_for(printed(proc, lines, "Ctrl-C stops everything"), 120, 0, what="the service to be ready")
        python_kids = [k for k in children(proc.pid) if "redis-server" not in Path(f"/proc/{k}/cmdline").read_text()]
        assert len(python_kids) == 2  # the worker and uvicorn
        for kid in python_kids:
            assert environ(kid).get("FASTMESH_WEBHOOK_SECRET") == "s3cret", Path(f"/proc/{kid}/cmdline").read_text()
        points = "".join(f"{x:.4f} {y:.4f} {z:.4f}\n" for x, y, z in trimesh.creation.icosphere(2).vertices)
        r = httpx.post(f"http://127.0.0.1:{port}/v1/jobs", files={"file": ("ball.xyz", points)},
                       data={"max_vertices": "16", "callback_url": receiver.url}, timeout=30)
        assert r.status_code == 202, r.text
        wait_for(lambda: receiver.calls, 120, 0.1, what="the webhook delivery")
        headers, body = receiver.calls[0]
        assert json.loads(body)["id"] == r.json()["id"]
        expected = "sha256=" + hmac.new(b"s3cret", body, hashlib.sha256).hexdigest()
        assert headers["x-fastmesh-signature"] == expected
    finally:
        receiver.close()
        proc.send_signal(signal.SIGINT)
        try:
            proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
