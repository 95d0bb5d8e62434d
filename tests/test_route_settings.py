"""What the job routes take from their app's settings, and how a request's faults are named.

The routers are module-level; each app's long-poll limit (``max_wait_seconds``) and default export formats
must still be that app's own, in the checks and in its OpenAPI schema, for two apps served side by side.
A request with several faults names them in the order of the schema: header, file, then the form fields.
"""

from __future__ import annotations

import httpx
import pytest
from stack import make_settings

from service.processes import ServedApp


@pytest.fixture(scope="module")
def two_apps(redis_url):
    """An app with default settings and one with a 2 s long poll exporting obj and ply by default."""
    plain = ServedApp(make_settings(redis_url, "routes-plain"))
    short = ServedApp(make_settings(redis_url, "routes-short", max_wait_seconds=2.0, default_formats=["obj", "ply"]))
    yield plain, short
    short.stop()
    plain.stop()


def error(r: httpx.Response, status: int) -> str:
    assert r.status_code == status, r.text
    assert set(r.json()["error"]) == {"code", "message"}, r.text
    return r.json()["error"]["message"]


def test_each_app_checks_and_documents_its_own_long_poll_limit(two_apps):
    plain, short = two_apps
    missing = f"/v1/jobs/{'0' * 32}/result"
    assert error(httpx.get(f"{short.url}{missing}", params={"wait": 3}), 422) == \
        "wait: Input should be less than or equal to 2"
    assert error(httpx.get(f"{short.url}{missing}", params={"wait": "nan"}), 422) == \
        "wait: Input should be less than or equal to 2"
    assert error(httpx.get(f"{short.url}{missing}", params={"wait": -1}), 422) == \
        "wait: Input should be greater than or equal to 0"
    assert error(httpx.get(f"{short.url}{missing}", params={"wait": 2}), 404)  # in range: the job is looked up
    assert error(httpx.get(f"{plain.url}{missing}", params={"wait": 3}), 404)
    for app, limit, formats in ((plain, 300.0, "glb"), (short, 2.0, "obj,ply")):
        spec = httpx.get(f"{app.url}/openapi.json").json()
        wait = next(p for p in spec["paths"]["/v1/jobs/{job_id}/result"]["get"]["parameters"]
                    if p["name"] == "wait")
        assert (wait["schema"]["minimum"], wait["schema"]["maximum"]) == (0, limit)
        for body in ("Body_submit_v1_jobs_post", "Body_submit_batch_v1_batches_post"):
            described = spec["components"]["schemas"][body]["properties"]["formats"]["description"]
            assert described.endswith(f"(default {formats}).")


def test_faults_are_named_in_the_schemas_order(two_apps):
    plain, _ = two_apps
    r = httpx.post(f"{plain.url}/v1/jobs", data={"seed": "-1", "top_k": "-1"},
                   headers={"Idempotency-Key": "k" * 201})
    fields = [part.split(":")[0] for part in error(r, 422).split("; ")]
    assert fields == ["Idempotency-Key", "file", "seed", "top_k"]
    r = httpx.post(f"{plain.url}/v1/batches", data={"candidates": "0"}, headers={"Idempotency-Key": "k" * 201})
    assert [part.split(":")[0] for part in error(r, 422).split("; ")] == ["Idempotency-Key", "files", "candidates"]


def test_unknown_and_repeated_fields_are_refused_on_both_forms(two_apps):
    plain, _ = two_apps
    files = {"file": ("a.xyz", b"0 0 0\n1 0 0\n0 1 0\n0 0 1\n")}
    assert "did you mean 'target_faces'" in error(
        httpx.post(f"{plain.url}/v1/jobs", files=files, data={"target_face": "300"}), 422)
    assert "file: sent 2 times" in error(
        httpx.post(f"{plain.url}/v1/jobs", files=[("file", ("a.xyz", b"0 0 0\n")), ("file", ("b.xyz", b"0 0 0\n"))]),
        422)
    assert "did you mean 'files'" in error(httpx.post(f"{plain.url}/v1/batches", files=files), 422)
