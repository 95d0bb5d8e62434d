"""A small client of the FastMesh HTTP service: submit, wait (with progress), download.

    from fastmesh.remote.client import Client
    c = Client("http://127.0.0.1:8000", api_key=None)
    job = c.submit("chair.ply", seed=1, formats="glb,obj")
    job = c.wait(job["id"], progress=lambda j: print(j["progress"]))
    c.download(job["id"], "chair.glb")

Errors of the service raise :class:`ServiceError` with its ``status``, ``code`` and ``message``.
Queue-full and rate-limit answers (429), and 409 with ``Retry-After`` (an upload with the same
Idempotency-Key still being processed), are retried after their ``Retry-After``.
"""

from __future__ import annotations

import os
import time
import uuid
from collections.abc import Callable
from pathlib import Path

import httpx

FINAL = ("succeeded", "failed", "cancelled")


def form_values(params: dict) -> dict[str, str]:
    """The form fields of a submission: each value set, as the service reads it (a bool as true or false);
    None (the service's default) left out."""
    return {k: (str(v).lower() if isinstance(v, bool) else str(v)) for k, v in params.items() if v is not None}


class ServiceError(RuntimeError):
    """An error answer of the service (or no answer: status 0, code 'unreachable')."""

    def __init__(self, status: int, code: str, message: str):
        super().__init__(f"{message} ({code}, HTTP {status})" if status else message)
        self.status, self.code, self.message = status, code, message


class JobFailed(ServiceError):
    """The job ended as failed or cancelled; ``job`` holds its last state."""

    def __init__(self, job: dict):
        err = job.get("error") or {}
        super().__init__(409, err.get("code", job["status"]), f"job {job['id']} {job['status']}: "
                                                               f"{err.get('message', 'no detail')}")
        self.job = job


class Client:
    """Synchronous client; ``api_key`` defaults to ``$FASTMESH_API_KEY``."""

    def __init__(self, url: str, api_key: str | None = None, timeout: float = 60.0, retries_429: int = 5):
        key = api_key if api_key is not None else os.environ.get("FASTMESH_API_KEY")
        headers = {"Authorization": f"Bearer {key}"} if key else {}
        self.http = httpx.Client(base_url=url.rstrip("/"), headers=headers, timeout=timeout)
        self.retries_429 = retries_429

    def close(self) -> None:
        self.http.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # ------------------------------------------------------------------ calls
    def _call(self, method: str, path: str, **kw) -> httpx.Response:
        for attempt in range(self.retries_429 + 1):
            try:
                r = self.http.request(method, path, **kw)
            except httpx.HTTPError as e:
                raise ServiceError(0, "unreachable", f"cannot reach {self.http.base_url}: {e}") from None
            later = r.status_code == 429 or (r.status_code == 409 and "Retry-After" in r.headers)
            if later and attempt < self.retries_429:
                time.sleep(min(60.0, float(r.headers.get("Retry-After", "1"))))
                continue
            if r.status_code >= 400:
                try:
                    err = r.json()["error"]
                    raise ServiceError(r.status_code, err["code"], err["message"])
                except (ValueError, KeyError, TypeError):
                    raise ServiceError(r.status_code, "http_error", r.text[:200]) from None
            return r
        raise AssertionError("unreachable")

    def submit(self, path: str | os.PathLike, idempotency_key: str | None = None, **params) -> dict:
        """Upload a shape file; ``params``: the form fields, by name (the fields of
        ``fastmesh.params.GenerateParams``, ``formats``, ``callback_url``), None for the service's default.  A retry
        after a lost answer returns the same job (Idempotency-Key)."""
        path = Path(path)
        data = path.read_bytes()
        fields = form_values(params)
        headers = {"Idempotency-Key": idempotency_key or uuid.uuid4().hex}
        return self._call("POST", "/v1/jobs", files={"file": (path.name, data)}, data=fields, headers=headers).json()

    def job(self, job_id: str) -> dict:
        return self._call("GET", f"/v1/jobs/{job_id}").json()

    def wait(self, job_id: str, progress: Callable[[dict], None] | None = None, timeout: float | None = None,
             interval: float = 0.25, max_interval: float = 2.0) -> dict:
        """Poll until the job is final; ``progress(job)`` on each change.  Raises JobFailed, TimeoutError."""
        deadline = None if timeout is None else time.monotonic() + timeout
        last = None
        while True:
            job = self.job(job_id)
            seen = (job["status"], job["progress"]["stage"], job["progress"]["fraction"])
            if progress and seen != last:
                progress(job)
            last = seen
            if job["status"] in FINAL:
                if job["status"] != "succeeded":
                    raise JobFailed(job)
                return job
            if deadline is not None and time.monotonic() > deadline:
                raise TimeoutError(f"job {job_id} still {job['status']} after {timeout:g} s")
            time.sleep(interval)
            interval = min(max_interval, interval * 1.3)

    def download(self, job_id: str, out: str | os.PathLike | None = None, fmt: str | None = None) -> bytes:
        """The result mesh (format from ``fmt`` or ``out``'s extension, default glb); written to ``out`` if given."""
        fmt = (fmt or (Path(out).suffix.lstrip(".") if out else "") or "glb").lower()
        data = self._call("GET", f"/v1/jobs/{job_id}/result", params={"format": fmt}).content
        if out is not None:
            Path(out).write_bytes(data)
        return data

    def cancel(self, job_id: str) -> dict | None:
        """Cancel a queued/running job (returns it) or delete a finished one (returns None)."""
        r = self._call("DELETE", f"/v1/jobs/{job_id}")
        return r.json() if r.status_code == 200 else None
