"""``POST /v1/batches``: several files, one set of parameters, a job each; all or nothing.  Unknown and
repeated form fields are refused on every form route.  Apps without a worker (jobs stay queued)."""

from __future__ import annotations

import httpx
import pytest
from stack import assert_error, make_settings, post, sphere_points, xyz_bytes

from fastmesh_jobs.store import Store
from service.processes import ServedApp

BALLS = [xyz_bytes(sphere_points(seed=i)) for i in range(4)]


@pytest.fixture(scope="module")
def idle(redis_url):
    app = ServedApp(make_settings(redis_url, "batches", max_queue_depth=6, max_batch_files=4))
    yield app
    app.stop()


def batch(app, files: list[tuple[str, bytes]], headers=None, **fields) -> httpx.Response:
    return httpx.post(f"{app.url}/v1/batches", files=[("files", f) for f in files],
                      data={k: str(v) for k, v in fields.items()}, headers=headers, timeout=60)


def queued_ids(app) -> set[str]:
    store = Store(app.settings)
    return {m.decode() for m in store.redis.zrange(store.k_queued, 0, -1)}


def empty_queue(app):
    for job_id in queued_ids(app):
        httpx.delete(f"{app.url}/v1/jobs/{job_id}")


def test_batch_makes_a_job_per_file_with_one_set_of_parameters(idle):
    r = batch(idle, [(f"b{i}.xyz", BALLS[i]) for i in range(3)], seed=7, target_faces=300, formats="obj")
    assert r.status_code == 202, r.text
    body = r.json()
    assert len(body["job_ids"]) == 3 and [j["id"] for j in body["jobs"]] == body["job_ids"]
    assert [j["input"]["filename"] for j in body["jobs"]] == ["b0.xyz", "b1.xyz", "b2.xyz"]
    for job in body["jobs"]:
        assert job["status"] == "queued"
        assert job["params"]["seed"] == 7 and job["params"]["target_faces"] == 300
        assert job["params"]["formats"] == ["obj"]
        assert httpx.get(f"{idle.url}/v1/jobs/{job['id']}").json()["id"] == job["id"]
    empty_queue(idle)


def test_a_bad_file_refuses_the_whole_batch(idle):
    before = queued_ids(idle)
    r = batch(idle, [("a.xyz", BALLS[0]), ("bad.xyz", b"not numbers at all\n"), ("c.xyz", BALLS[1])])
    err = assert_error(r, 422)
    assert err["message"].startswith("files[1] 'bad.xyz': "), err
    r = batch(idle, [("a.xyz", BALLS[0]), ("x.doc", b"hello")])
    assert assert_error(r, 415, "unsupported_format")["message"].startswith("files[1] 'x.doc'")
    assert queued_ids(idle) == before  # no job was created


def test_batch_limits(idle):
    r = batch(idle, [(f"b{i}.xyz", BALLS[0]) for i in range(5)])
    assert "at most 4" in assert_error(r, 422, "too_many_files")["message"]
    assert "files" in assert_error(httpx.post(f"{idle.url}/v1/batches", data={"seed": "1"}), 422)["message"]
    # Room in the queue for some of the files but not all: nothing is queued.
    ok = batch(idle, [(f"b{i}.xyz", BALLS[i]) for i in range(4)])
    assert ok.status_code == 202, ok.text
    assert_error(batch(idle, [("a.xyz", BALLS[0]), ("b.xyz", BALLS[1]), ("c.xyz", BALLS[2])]), 429, "queue_full")
    assert queued_ids(idle) == set(ok.json()["job_ids"])
    empty_queue(idle)
    assert_error(batch(idle, [("a.xyz", BALLS[0])], seed=-1), 422, "invalid_parameter")


def test_batch_idempotency_key_returns_the_same_jobs(idle):
    files = [("a.xyz", BALLS[0]), ("b.xyz", BALLS[1])]
    first = batch(idle, files, headers={"Idempotency-Key": "batch-1"})
    again = batch(idle, files, headers={"Idempotency-Key": "batch-1"})
    assert first.status_code == 202 and again.status_code == 200, again.text
    assert again.json()["job_ids"] == first.json()["job_ids"]
    empty_queue(idle)


@pytest.mark.parametrize("route, files", [("/v1/jobs", [("file", ("a.xyz", BALLS[0]))]),
                                          ("/v1/batches", [("files", ("a.xyz", BALLS[0]))])])
def test_unknown_or_repeated_form_fields_are_422_naming_the_field(idle, route, files):
    before = queued_ids(idle)
    r = httpx.post(f"{idle.url}{route}", files=files, data={"target_face": "500"})
    err = assert_error(r, 422, "unknown_field")
    assert err["message"].startswith("target_face: unknown field; did you mean 'target_faces'?"), err
    r = httpx.post(f"{idle.url}{route}", files=files, data={"colour": "red"})
    assert assert_error(r, 422, "unknown_field")["message"].startswith("colour: unknown field; the fields are ")
    r = httpx.post(f"{idle.url}{route}", files=files, data={"seed": ["1", "2"]})
    assert assert_error(r, 422, "invalid_parameter")["message"] == "seed: sent 2 times; send it once"
    assert queued_ids(idle) == before


def test_one_file_field_per_job_and_files_for_a_batch(idle):
    r = httpx.post(f"{idle.url}/v1/jobs", files=[("file", ("a.xyz", BALLS[0])), ("file", ("b.xyz", BALLS[1]))])
    assert "file: sent 2 times" in assert_error(r, 422)["message"]
    r = httpx.post(f"{idle.url}/v1/jobs", files=[("files", ("a.xyz", BALLS[0]))])
    assert "did you mean 'file'?" in assert_error(r, 422, "unknown_field")["message"]
    assert post(idle.url, "a.xyz", BALLS[0], target_faces=500).json()["params"]["target_faces"] == 500
    empty_queue(idle)


def test_a_failure_while_creating_deletes_the_jobs_made(idle, monkeypatch):
    """The queue filling between the check and the second job (other submissions racing): the first job is
    deleted, and the batch is answered 429 as a whole."""
    from fastmesh_jobs.limits import QueueFull

    store = idle.app.state.store
    real, calls = store.create, []

    def create(*args, **kw):
        calls.append(kw["job_id"])
        if len(calls) == 2:
            raise QueueFull(kw["job_id"])
        return real(*args, **kw)

    monkeypatch.setattr(store, "create", create)
    before = queued_ids(idle)
    r = batch(idle, [("a.xyz", BALLS[0]), ("b.xyz", BALLS[1]), ("c.xyz", BALLS[2])])
    assert_error(r, 429, "queue_full")
    assert len(calls) == 2 and queued_ids(idle) == before
    assert store.get(calls[0]) is None and store.get_input(calls[0]) is None
    assert httpx.get(f"{idle.url}/v1/jobs/{calls[0]}").status_code == 404
    listed = httpx.get(f"{idle.url}/v1/jobs", params={"limit": 100}).json()["jobs"]
    assert calls[0] not in {j["id"] for j in listed}
