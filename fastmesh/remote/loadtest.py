"""Load-testing a FastMesh service: many clients that upload, poll and download like real users.

    from fastmesh.remote.loadtest import LoadConfig, run
    report = run(LoadConfig(url="http://127.0.0.1:8000", inputs=["shapes/"], concurrency=4, jobs=20))
    print(format_report(report))

Each of ``concurrency`` virtual users loops: upload a file (``POST /v1/jobs``), poll
``GET /v1/jobs/{id}`` with a growing interval (0.25 s x 1.5 up to 2 s, like :mod:`fastmesh.remote.client`),
download the result, then take the next file.  A 429 is waited out for its ``Retry-After``; a
refused connection or a 5xx (an API restarting, Redis away) is retried with back-off, the same
``Idempotency-Key`` reused so a retried upload never makes a second job.

The run is bounded: it stops submitting after ``jobs`` uploads or ``duration`` seconds (whichever
comes first; 20 jobs when neither is given), then waits at most ``grace`` seconds for the accepted
jobs.  An accepted job that has not finished by then (or whose id the service forgot) is *lost*.

Like :mod:`fastmesh.remote.client` this module talks HTTP (httpx); nothing else in the library imports it.
"""

from __future__ import annotations

import asyncio
import itertools
import os
import time
import uuid
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import numpy as np

from ..shapes.shape import SUPPORTED_FORMATS

FINAL = ("succeeded", "failed", "cancelled")
PERCENTILES = (50, 95, 99)
DEFAULT_JOBS = 20


@dataclass
class LoadConfig:
    """What to run.  Times in seconds.

    Attributes
    ----------
    url : str
        Service address, e.g. ``http://127.0.0.1:8000``.
    inputs : list of path
        Files, or directories whose files of a supported format are used (sorted, round-robin).
    concurrency : int
        Virtual users, each with at most one job in flight.
    jobs : int or None
        Uploads to make in total (accepted or not).  None with ``duration`` None means 20.
    duration : float or None
        Stop starting new uploads after this long.
    grace : float
        After submitting stops, how long accepted jobs may still take before they count as lost.
    params : dict
        Form fields sent with every upload (``seed``, ``max_vertices``, ``formats``, ...).
    fmt : str
        Result format downloaded (``glb``, ``obj``, ``ply``).
    """

    url: str
    inputs: list[str | os.PathLike]
    concurrency: int = 4
    jobs: int | None = None
    duration: float | None = None
    grace: float = 60.0
    api_key: str | None = None
    params: dict = field(default_factory=dict)
    fmt: str = "glb"
    poll_interval: float = 0.25
    max_poll_interval: float = 2.0
    http_timeout: float = 60.0


def input_files(inputs: list[str | os.PathLike]) -> list[Path]:
    """The files to upload: given files as they are, directories' supported files sorted by name."""
    out: list[Path] = []
    for item in inputs:
        p = Path(item)
        if p.is_dir():
            out += sorted(f for f in p.iterdir() if f.is_file() and f.suffix.lower().lstrip(".") in SUPPORTED_FORMATS)
        elif p.is_file():
            out.append(p)
        else:
            raise FileNotFoundError(f"no such file or directory: {p}")
    if not out:
        raise ValueError(f"no input files of a supported format ({', '.join(SUPPORTED_FORMATS)}) in "
                         f"{', '.join(map(str, inputs))}")
    return out


def percentiles(xs: list[float], qs: tuple[int, ...] = PERCENTILES) -> dict[str, float | None]:
    """``{"p50": .., "p95": .., "p99": .., "mean": .., "n": ..}``; None values when ``xs`` is empty."""
    if not xs:
        return {**{f"p{q}": None for q in qs}, "mean": None, "n": 0}
    a = np.asarray(xs, dtype=np.float64)
    return {**{f"p{q}": round(float(np.percentile(a, q)), 4) for q in qs}, "mean": round(float(a.mean()), 4),
            "n": len(xs)}


class _Run:
    """Shared state of one run: counters, deadlines, the records of every job."""

    def __init__(self, cfg: LoadConfig, files: list[Path]):
        self.cfg = cfg
        self.files = [(f.name, f.read_bytes()) for f in files]
        self.next_file = itertools.cycle(range(len(self.files)))
        self.limit = cfg.jobs if cfg.jobs is not None else (None if cfg.duration is not None else DEFAULT_JOBS)
        self.t0 = time.monotonic()
        self.submit_until = self.t0 + cfg.duration if cfg.duration is not None else float("inf")
        self.started = 0
        self.http: Counter[str] = Counter()         # "GET /v1/jobs/{id} 200" -> n
        self.errors: Counter[str] = Counter()       # "429", "503", "transport" -> n
        self.missing_retry_after = 0                # 429s without a Retry-After header
        self.records: list[dict] = []
        self.submit_stopped_at: float | None = None
        self.uploading = 0                          # uploads between their first try and their answer
        self.last_upload_end = self.t0

    @property
    def deadline(self) -> float:
        """When waiting for accepted jobs ends: ``grace`` after submitting stopped and the last upload was answered."""
        if self.submit_stopped_at is None or self.uploading:
            return float("inf")
        return max(self.submit_stopped_at, self.last_upload_end) + self.cfg.grace

    def take(self) -> int | None:
        """Claim the next upload (its index), or None when the run stops submitting."""
        if (self.limit is not None and self.started >= self.limit) or time.monotonic() >= self.submit_until:
            if self.submit_stopped_at is None:
                self.submit_stopped_at = time.monotonic()
            return None
        self.started += 1
        return next(self.next_file)

    def count(self, method: str, route: str, status: int | str) -> None:
        self.http[f"{method} {route} {status}"] += 1
        if status == "transport" or int(status) >= 400:
            self.errors[str(status)] += 1


async def _request(run: _Run, http: httpx.AsyncClient, method: str, url: str, route: str,
                   until: Callable[[], float], **kw) -> httpx.Response | None:
    """One logical request: retried on 429 and 409 + Retry-After (after it), 5xx and connection errors until
    ``until()``.

    Returns the first answer that is neither, or None when the deadline passed first.
    """
    backoff = 0.25
    while time.monotonic() < (deadline := until()):
        try:
            r = await http.request(method, url, **kw)
        except httpx.HTTPError:
            run.count(method, route, "transport")
            await asyncio.sleep(min(backoff, max(0.0, deadline - time.monotonic())))
            backoff = min(backoff * 2, 4.0)
            continue
        run.count(method, route, r.status_code)
        # 429, and 409 with Retry-After (the same Idempotency-Key still being processed): "later".
        if r.status_code == 429 or (r.status_code == 409 and "Retry-After" in r.headers):
            ra = r.headers.get("Retry-After")
            if ra is None:
                run.missing_retry_after += 1
            try:
                wait = float(ra) if ra is not None else backoff
            except ValueError:
                wait = backoff
            await asyncio.sleep(min(wait, max(0.0, deadline - time.monotonic())))
            continue
        if r.status_code >= 500:
            await asyncio.sleep(min(backoff, max(0.0, deadline - time.monotonic())))
            backoff = min(backoff * 2, 4.0)
            continue
        return r
    return None


async def _one_job(run: _Run, http: httpx.AsyncClient, index: int) -> dict:
    cfg = run.cfg
    name, data = run.files[index]
    rec: dict = {"file": name, "outcome": None, "id": None}
    t_start = time.monotonic()
    key = uuid.uuid4().hex  # the same key on every retry of this upload: never two jobs for one upload
    # A 429 means "later", not "never": an upload is retried for up to ``grace`` seconds (and not past
    # ``grace`` after the end of ``duration``); then it counts as not submitted.
    upload_until = min(t_start, run.submit_until) + cfg.grace
    run.uploading += 1
    try:
        r = await _request(run, http, "POST", "/v1/jobs", "/v1/jobs", lambda: upload_until,
                           files={"file": (name, data)}, data=cfg.params, headers={"Idempotency-Key": key})
    finally:
        run.uploading -= 1
        run.last_upload_end = max(run.last_upload_end, time.monotonic())
    if r is None:
        rec["outcome"] = "not_submitted"
        return rec
    if r.status_code not in (200, 202):
        rec["outcome"], rec["error"] = "rejected", _error_code(r)
        return rec
    job = r.json()
    rec["id"] = job["id"]
    t_accepted = time.monotonic()
    rec["submit_s"] = t_accepted - t_start
    interval = cfg.poll_interval
    route = "/v1/jobs/{id}"
    while job["status"] not in FINAL:
        if time.monotonic() + interval > run.deadline:
            rec["outcome"], rec["last_status"] = "lost", job["status"]
            return rec
        await asyncio.sleep(interval)
        interval = min(cfg.max_poll_interval, interval * 1.5)
        r = await _request(run, http, "GET", f"/v1/jobs/{job['id']}", route, lambda: run.deadline)
        if r is None:
            rec["outcome"], rec["last_status"] = "lost", job["status"]
            return rec
        if r.status_code != 200:  # 404: the service forgot an accepted job
            rec["outcome"], rec["last_status"] = "lost", f"HTTP {r.status_code} {_error_code(r)}"
            return rec
        job = r.json()
    rec["status"], rec["timings"] = job["status"], job.get("timings") or {}
    if job["status"] != "succeeded":
        rec["outcome"], rec["error"] = job["status"], (job.get("error") or {}).get("code", job["status"])
        rec["end_to_end_s"] = time.monotonic() - t_start
        return rec
    r = await _request(run, http, "GET", f"/v1/jobs/{job['id']}/result", "/v1/jobs/{id}/result",
                       lambda: run.deadline, params={"format": cfg.fmt})
    if r is None or r.status_code != 200:
        rec["outcome"], rec["error"] = "download_failed", None if r is None else _error_code(r)
        return rec
    rec["outcome"], rec["bytes"] = "succeeded", len(r.content)
    rec["end_to_end_s"] = time.monotonic() - t_start
    rec["result"] = job.get("result")
    return rec


def _error_code(r: httpx.Response) -> str:
    try:
        return f"{r.status_code} {r.json()['error']['code']}"
    except (ValueError, KeyError, TypeError):
        return str(r.status_code)


async def _user(run: _Run, http: httpx.AsyncClient) -> None:
    while (index := run.take()) is not None:
        run.records.append(await _one_job(run, http, index))


async def run_async(cfg: LoadConfig) -> dict:
    """Run the load test; returns the report (see :func:`summarize`)."""
    if cfg.concurrency < 1:
        raise ValueError("concurrency must be at least 1")
    if cfg.jobs is not None and cfg.jobs < 1:
        raise ValueError("jobs must be at least 1")
    if cfg.duration is not None and cfg.duration <= 0:
        raise ValueError("duration must be positive")
    files = input_files(cfg.inputs)
    run = _Run(cfg, files)
    headers = {"Authorization": f"Bearer {cfg.api_key}"} if cfg.api_key else {}
    limits = httpx.Limits(max_connections=cfg.concurrency + 4, max_keepalive_connections=cfg.concurrency + 4)
    async with httpx.AsyncClient(base_url=cfg.url.rstrip("/"), headers=headers, timeout=cfg.http_timeout,
                                 limits=limits) as http:
        await asyncio.gather(*(_user(run, http) for _ in range(cfg.concurrency)))
    return summarize(run.records, time.monotonic() - run.t0, run.http, run.errors, run.missing_retry_after,
                     cfg, [f.name for f in files])


def run(cfg: LoadConfig) -> dict:
    """Synchronous wrapper of :func:`run_async`."""
    return asyncio.run(run_async(cfg))


def summarize(records: list[dict], wall: float, http: Counter, errors: Counter, missing_retry_after: int,
              cfg: LoadConfig, files: list[str]) -> dict:
    """The report: counts, rates, percentiles (seconds), stage timings, HTTP answers, lost job ids."""
    ok = [r for r in records if r["outcome"] == "succeeded"]
    accepted = [r for r in records if r["id"] is not None]
    outcomes = Counter(r["outcome"] for r in records)
    stage_keys = sorted({k for r in ok for k, v in r["timings"].items() if v is not None})
    done_at = [r for r in records if r.get("end_to_end_s") is not None]
    return {
        "url": cfg.url, "concurrency": cfg.concurrency, "jobs_requested": cfg.jobs, "duration_requested": cfg.duration,
        "inputs": files, "params": cfg.params,
        "wall_s": round(wall, 3),
        "jobs": {"started": len(records), "accepted": len(accepted), "succeeded": len(ok),
                 "failed": outcomes.get("failed", 0), "cancelled": outcomes.get("cancelled", 0),
                 "rejected": outcomes.get("rejected", 0), "not_submitted": outcomes.get("not_submitted", 0),
                 "download_failed": outcomes.get("download_failed", 0), "lost": outcomes.get("lost", 0)},
        "jobs_per_minute": round(len(ok) / wall * 60.0, 2) if wall > 0 and done_at else 0.0,
        "end_to_end_s": percentiles([r["end_to_end_s"] for r in ok]),
        "queue_wait_s": percentiles([r["timings"]["queue"] for r in ok if r["timings"].get("queue") is not None]),
        "stages_s": {k: percentiles([r["timings"][k] for r in ok if r["timings"].get(k) is not None])
                     for k in stage_keys},
        "job_errors": dict(Counter(r["error"] for r in records if r.get("error"))),
        "http_errors": dict(sorted(errors.items())),
        "http": dict(sorted(http.items())),
        "retry_after_missing": missing_retry_after,
        "lost_ids": [r["id"] for r in records if r["outcome"] == "lost"],
    }


NAME_WIDTH = 22  # the first column of the text report
STAGE_LABELS = {"total": "total (no queue)"}


def _seconds(x: float | None) -> str:
    return "-" if x is None else f"{x:.2f} s"


def format_report(rep: dict) -> str:
    """The report as a few aligned lines for a terminal."""
    j = rep["jobs"]
    lines = [f"{rep['url']}  concurrency {rep['concurrency']}  inputs {len(rep['inputs'])}  wall {rep['wall_s']:.1f} s",
             f"jobs: {j['started']} started, {j['accepted']} accepted, {j['succeeded']} succeeded, "
             f"{j['failed']} failed, {j['rejected']} rejected, {j['lost']} lost"
             + (f", {j['not_submitted']} not submitted" if j["not_submitted"] else "")
             + (f", {j['download_failed']} download failed" if j["download_failed"] else ""),
             f"throughput: {rep['jobs_per_minute']:.1f} jobs/minute; job latency (upload to result) "
             f"p50 {_seconds(rep['end_to_end_s']['p50'])}, p95 {_seconds(rep['end_to_end_s']['p95'])}", "",
             f"{'seconds':<{NAME_WIDTH}}{'p50':>9}{'p95':>9}{'p99':>9}{'mean':>9}{'n':>6}"]

    def f(x: float | None) -> str:
        return f"{x:9.3f}" if x is not None else f"{'-':>9}"

    def row(name: str, p: dict) -> str:
        return f"{name:<{NAME_WIDTH}}{f(p['p50'])}{f(p['p95'])}{f(p['p99'])}{f(p['mean'])}{p['n']:>6}"

    lines.append(row("end-to-end", rep["end_to_end_s"]))
    lines.append(row("queue wait", rep["queue_wait_s"]))
    # The job's own "total" is the sum of its stages, the queue wait apart: last, and named so.
    stages = sorted((k for k in rep["stages_s"] if k != "queue"), key=lambda k: k == "total")
    for k in stages:
        lines.append(row(f"  {STAGE_LABELS.get(k, k)}", rep["stages_s"][k]))
    if rep["http_errors"]:
        lines.append("http errors: " + ", ".join(f"{k}: {v}" for k, v in rep["http_errors"].items()))
    if rep["job_errors"]:
        lines.append("job errors: " + ", ".join(f"{k}: {v}" for k, v in rep["job_errors"].items()))
    if rep["retry_after_missing"]:
        lines.append(f"429 answers without Retry-After: {rep['retry_after_missing']}")
    if rep["lost_ids"]:
        lines.append("lost: " + " ".join(rep["lost_ids"][:20]) + (" ..." if len(rep["lost_ids"]) > 20 else ""))
    return "\n".join(lines)
