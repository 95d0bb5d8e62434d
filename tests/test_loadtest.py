"""``fastmesh loadtest`` against the real stack: Redis, the API over HTTP, a ``fastmesh-worker`` process."""

from __future__ import annotations

import json
import subprocess
import sys
from collections import Counter

import httpx
import pytest
from stack import make_settings, wp, write_inputs

from fastmesh.remote.loadtest import LoadConfig, format_report, percentiles, run, summarize
from service.processes import ServedApp, free_port


@pytest.fixture(scope="module")
def served(redis_url, weights, tmp_path_factory):
    s = make_settings(redis_url, "load", weights=weights, api_keys=["lt-key"])
    app = ServedApp(s)
    worker = wp(s, "load-w", tmp_path_factory.mktemp("logs") / "w.log").wait_ready()
    yield app
    worker.stop()
    app.stop()


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    return write_inputs(tmp_path_factory.mktemp("inputs"), n=2)


def cli(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "fastmesh.cli", "loadtest", *args], capture_output=True, text=True,
                          timeout=timeout)


def test_cli_json_report_against_real_stack(served, inputs):
    r = cli("--url", served.url, "--inputs", str(inputs), "--concurrency", "3", "--jobs", "7", "--json",
            "--api-key", "lt-key", "--max-vertices", "10", "--seed", "2", "--format", "obj")
    assert r.returncode == 0, r.stderr + r.stdout
    rep = json.loads(r.stdout)
    assert rep["jobs"] == {"started": 7, "accepted": 7, "succeeded": 7, "failed": 0, "cancelled": 0, "rejected": 0,
                           "not_submitted": 0, "download_failed": 0, "lost": 0}
    assert rep["lost_ids"] == [] and rep["http_errors"] == {}
    assert rep["params"] == {"seed": "2", "max_vertices": "10"}
    assert sorted(rep["inputs"]) == ["ball0.xyz", "ball1.xyz", "cloud.npy", "ico.obj"]
    assert rep["jobs_per_minute"] > 0
    assert rep["http"]["POST /v1/jobs 202"] == 7 and rep["http"]["GET /v1/jobs/{id}/result 200"] == 7
    for p in (rep["end_to_end_s"], rep["queue_wait_s"]):
        assert p["n"] == 7 and 0 <= p["p50"] <= p["p95"] <= p["p99"], p
    # Stage timings come from the jobs' metadata (the worker's measurements), not from the client.
    assert {"load", "encode", "vertices", "faces", "export", "total"} <= set(rep["stages_s"])
    assert rep["stages_s"]["total"]["p50"] <= rep["end_to_end_s"]["p99"]


def test_cli_text_report_duration_bounded(served, inputs):
    r = cli("--url", served.url, "--inputs", str(inputs / "ball0.xyz"), "--duration", "1.5", "-c", "2",
            "--api-key", "lt-key", "--max-vertices", "8")
    assert r.returncode == 0, r.stderr + r.stdout
    assert "jobs/minute" in r.stdout and "end-to-end" in r.stdout and "queue wait" in r.stdout
    assert " 0 lost" in r.stdout


def test_rejections_429_and_lost_jobs_are_reported(redis_url, inputs, tmp_path):
    """No worker, a queue of 2: two jobs are accepted and never finish (lost), the others meet 429 + Retry-After
    until they give up; a broken file is rejected with its 4xx code."""
    app = ServedApp(make_settings(redis_url, "noworker", max_queue_depth=2))
    try:
        (tmp_path / "a.xyz").write_bytes((inputs / "ball0.xyz").read_bytes())
        (tmp_path / "b.ply").write_bytes(b"ply\nformat nonsense\n")
        rep = run(LoadConfig(url=app.url, inputs=[tmp_path / "a.xyz"], concurrency=4, jobs=4, grace=1.5))
        assert rep["jobs"]["accepted"] == 2 and rep["jobs"]["lost"] == 2 and rep["jobs"]["succeeded"] == 0
        assert rep["jobs"]["not_submitted"] == 2
        assert len(rep["lost_ids"]) == 2 and all(len(i) == 32 for i in rep["lost_ids"])
        assert rep["http_errors"]["429"] >= 2 and rep["retry_after_missing"] == 0
        assert "lost: " in format_report(rep)
        for job_id in rep["lost_ids"]:  # make room: the queue is checked before the file is parsed
            assert httpx.delete(f"{app.url}/v1/jobs/{job_id}").status_code == 200
        rep = run(LoadConfig(url=app.url, inputs=[tmp_path / "b.ply"], concurrency=1, jobs=1, grace=1))
        assert rep["jobs"]["rejected"] == 1 and rep["job_errors"] == {"422 unreadable": 1}
        assert rep["http_errors"] == {"422": 1}
    finally:
        app.stop()


def test_cli_usage_errors(tmp_path):
    r = cli("--url", "http://127.0.0.1:9", "--inputs", str(tmp_path))
    assert r.returncode == 2 and "no input files" in r.stderr and "Traceback" not in r.stderr
    (tmp_path / "a.xyz").write_text("0 0 0\n")
    r = cli("--url", f"http://127.0.0.1:{free_port()}", "--inputs", str(tmp_path))
    assert r.returncode == 1 and "cannot reach" in r.stderr and "Traceback" not in r.stderr
    r = cli("--url", "http://x", "--inputs", str(tmp_path / "missing"))
    assert r.returncode == 2 and "no such file" in r.stderr


def test_percentiles():
    p = percentiles([1.0, 2.0, 3.0, 4.0, 100.0])
    assert p["p50"] == 3.0 and p["n"] == 5 and p["p50"] <= p["p95"] <= p["p99"] <= 100
    assert percentiles([]) == {"p50": None, "p95": None, "p99": None, "mean": None, "n": 0}


def test_text_report_names_the_total_as_without_the_queue():
    """The job's "total" is the sum of its stages, the queue wait apart; the table says so and puts it last."""
    rec = {"outcome": "succeeded", "id": "a", "end_to_end_s": 5.2, "error": None,
           "timings": {"queue": 2.0, "load": 0.1, "vertices": 2.5, "total": 2.6}}
    rep = summarize([rec], 10.0, Counter(), Counter(), 0, LoadConfig(url="http://x", inputs=[]), [])
    rows = [line.split()[0:3] for line in format_report(rep).splitlines() if line.startswith("  ")]
    assert rows == [["load", "0.100", "0.100"], ["vertices", "2.500", "2.500"], ["total", "(no", "queue)"]]
    assert "throughput: 6.0 jobs/minute; job latency (upload to result) p50 5.20 s, p95 5.20 s" in format_report(rep)
    none = summarize([], 1.0, Counter(), Counter(), 0, LoadConfig(url="http://x", inputs=[]), [])
    assert "job latency (upload to result) p50 -, p95 -" in format_report(none)
