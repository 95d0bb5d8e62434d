"""``X-Queue-Position``: a queued job's place in the queue, counted from 0 (the next job a free worker takes), on
``POST /v1/jobs`` and ``GET /v1/jobs/{id}``, and README says so."""

from __future__ import annotations

import re
from pathlib import Path

import httpx
from stack import make_settings, post, sphere_points, xyz_bytes

from service.processes import ServedApp

README = (Path(__file__).resolve().parents[1] / "README.md").read_text()


def test_queue_position_counts_from_zero(redis_url):
    app = ServedApp(make_settings(redis_url, "position"))  # no worker: every job stays queued
    try:
        data = xyz_bytes(sphere_points(200))
        posted = [post(app.url, "ball.xyz", data, seed=i) for i in range(3)]
        assert [r.status_code for r in posted] == [202] * 3, [r.text for r in posted]
        assert [r.headers["X-Queue-Position"] for r in posted] == ["0", "1", "2"]
        ids = [r.json()["id"] for r in posted]
        assert httpx.delete(f"{app.url}/v1/jobs/{ids[0]}").status_code in (200, 202, 204)
        now = [httpx.get(f"{app.url}/v1/jobs/{i}") for i in ids]
        assert "X-Queue-Position" not in now[0].headers  # cancelled: no longer queued
        assert [r.headers["X-Queue-Position"] for r in now[1:]] == ["0", "1"]
    finally:
        app.stop()


def test_readme_says_where_the_queue_position_counts_from():
    said = [s for s in re.split(r"(?<=[.;])\s", README) if "X-Queue-Position" in s]
    assert said and all(re.search(r"counts? from 0|0-based|0 is the next", s) for s in said), said
