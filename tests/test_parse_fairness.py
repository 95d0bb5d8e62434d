"""Parsing is fair between API keys, and what an upload may cost to parse is bounded before it is parsed: lines
and values the shape never uses (a PLY element other than vertices and faces, OBJ ``vt`` lines) count like the
rest."""

from __future__ import annotations

import threading
import time

import httpx
import pytest
from stack import assert_error, make_settings, post, sphere_points, xyz_bytes

import fastmesh.shapes.io
import service.routes.jobs
from fastmesh.shapes.io import load_shape
from fastmesh.shapes.precheck import count_lines, count_words, parse_budget
from fastmesh.shapes.shape import ShapeError
from service.parse_slots import FairSlots
from service.processes import ServedApp

KEY, KEY2 = "fair-test-key", "fair-test-key-2"


def junk_ply(rows: int, vertices: int = 200) -> bytes:
    """An ASCII PLY of a few vertices and an element no shape uses: ``rows`` lists of 200 zeros."""
    points = sphere_points(vertices)
    head = (f"ply\nformat ascii 1.0\nelement vertex {vertices}\nproperty float x\nproperty float y\n"
            f"property float z\nelement junk {rows}\nproperty list uchar int v\nend_header\n").encode()
    return head + xyz_bytes(points, "%.5f") + (b"200" + b" 0" * 200 + b"\n") * rows


def vt_obj(lines: int, vertices: int = 200) -> bytes:
    """An OBJ of a few vertices and ``lines`` texture coordinates that nothing uses."""
    return b"".join(b"v " + row for row in xyz_bytes(sphere_points(vertices), "%.5f").splitlines(True)) + \
        b"vt 0 0\n" * lines


def bearer(key: str) -> dict:
    return {"Authorization": f"Bearer {key}"}


@pytest.fixture
def no_parser(monkeypatch):
    """The parser must not be reached: the parse budget refuses first."""
    def refuse(*_):
        raise AssertionError("the parser ran")

    monkeypatch.setattr(fastmesh.shapes.io, "_load_trimesh", refuse)


# ---------------------------------------------------------------------------------------- the parse budget


def test_the_counts_are_those_of_a_text_parser():
    data = b"v 1 2 3\r\nvt\t0 0\rf 1/1 2/2 3/3\n\n# x"
    assert count_words(data) == len(data.split()) == 13
    assert count_lines(data) == len(data.replace(b"\r\n", b"\n").replace(b"\r", b"\n").split(b"\n")) == 5


def test_an_unused_ply_element_past_the_budget_is_refused_before_it_is_parsed(no_parser):
    """The issue's upload: 148,148 rows of 200 zeros in an element nothing reads (60 MB, 30 M values)."""
    data = junk_ply(148_148)
    with pytest.raises(ShapeError) as e:
        load_shape(data, filename="junk.ply", max_points=500_000, max_faces=1_000_000)
    _, values = parse_budget("ply", 500_000, 1_000_000)
    assert e.value.code == "too_large"
    assert f"has {count_words(data)} values to read, over the limit of {values} values" in e.value.message
    assert "'junk' (148148 rows) not used" in e.value.message


def test_unused_obj_lines_past_the_budget_are_refused_before_they_are_parsed(no_parser):
    """The issue's other upload: 8 M ``vt`` lines."""
    with pytest.raises(ShapeError) as e:
        load_shape(vt_obj(8_000_000), filename="vt.obj", max_points=500_000, max_faces=1_000_000)
    lines, _ = parse_budget("obj", 500_000, 1_000_000)
    assert e.value.code == "too_large" and f"over the limit of {lines} lines" in e.value.message


def test_comment_lines_of_a_text_point_file_count_too():
    points = xyz_bytes(sphere_points(100))
    with pytest.raises(ShapeError) as e:
        load_shape(b"# nothing\n" * 20_000 + points, filename="c.xyz", max_points=1_000)
    lines, _ = parse_budget("xyz", 1_000, 0)
    assert e.value.code == "too_large" and f"20100 lines exceed the limit of {lines} lines" in e.value.message
    assert len(load_shape(b"# a few\n" * 500 + points, filename="c.xyz", max_points=1_000).vertices) == 100


def test_files_within_the_budget_still_load():
    lines, values = parse_budget("ply", 2_000, 4_000)
    rows = (values - 5_000) // 201  # an unused element, but within what the limits allow
    data = junk_ply(rows)
    assert count_words(data) < values and count_lines(data) < lines
    assert len(load_shape(data, filename="junk.ply", max_points=2_000, max_faces=4_000, normals=False).vertices) \
        == 200
    assert len(load_shape(vt_obj(5_000), filename="vt.obj", max_points=2_000, max_faces=4_000,
                          normals=False).vertices) == 200


# ---------------------------------------------------------------------------------------- over HTTP, two keys


@pytest.fixture(scope="module")
def app(redis_url):
    served = ServedApp(make_settings(redis_url, "fair", api_keys=[KEY, KEY2], max_queue_depth=10_000,
                                     max_points=20_000, max_faces=40_000))
    yield served
    served.stop()


@pytest.mark.parametrize("name,data", [("junk.ply", junk_ply(3_000)), ("vt.obj", vt_obj(150_000))],
                         ids=["ply-element", "obj-vt"])
def test_an_upload_over_the_parse_budget_is_a_413_naming_it(app, name, data):
    lines, values = parse_budget(name[-3:], 20_000, 40_000)
    error = assert_error(post(app.url, name, data, bearer(KEY)), 413, "too_large")
    assert f"over the limit of {values} values" in error["message"] or \
        f"over the limit of {lines} lines" in error["message"], error
    assert "20000 points and 40000 faces" in error["message"], error


def test_one_keys_slow_uploads_do_not_starve_another_keys(app, monkeypatch):
    """Key 1 sends as many uploads as there are slots, each slow to parse (held in its parse until key 2 is done);
    key 2's 14 small uploads meanwhile are all accepted, and key 1's last upload is the one told to retry."""
    release, started = threading.Event(), []
    parse_timed = service.routes.jobs.parse_timed

    def slow(parses, settings, data, filename, texture=False):
        if filename.startswith("slow"):
            started.append(filename)
            assert release.wait(60), "key 2's uploads did not finish"
        return parse_timed(parses, settings, data, filename, texture)

    monkeypatch.setattr(service.routes.jobs, "parse_timed", slow)
    small = xyz_bytes(sphere_points(50))
    slow_answers: list[httpx.Response] = []
    slots = app.settings.max_concurrent_parses
    threads = [threading.Thread(target=lambda i=i: slow_answers.append(
        post(app.url, f"slow{i}.xyz", small, bearer(KEY)))) for i in range(slots)]
    try:
        for t in threads:
            t.start()
        deadline = time.monotonic() + 30
        while len(started) < slots - 1 and time.monotonic() < deadline:
            time.sleep(0.02)
        time.sleep(0.3)  # key 1's last upload waits for a slot (or, unfairly, holds the last one)
        answers = [post(app.url, f"small{i}.xyz", small, bearer(KEY2)) for i in range(14)]
        assert [r.status_code for r in answers] == [202] * 14, [r.text[:200] for r in answers if r.status_code != 202]
        assert len(started) == slots - 1 and not release.is_set()  # key 1's uploads were still being parsed
        deadline = time.monotonic() + 30
        while not slow_answers and time.monotonic() < deadline:  # key 1's last upload gives up waiting for a slot
            time.sleep(0.02)
        assert len(slow_answers) == 1 and len(started) == slots - 1  # while its others are still being parsed
    finally:
        release.set()
        for t in threads:
            t.join(60)
    codes = sorted(r.status_code for r in slow_answers)
    assert codes == [202] * (slots - 1) + [429], [r.text[:200] for r in slow_answers]
    busy = assert_error(next(r for r in slow_answers if r.status_code == 429), 429, "busy")
    assert "this key's uploads" in busy["message"], busy


# ---------------------------------------------------------------------------------------- the slots


def test_a_freed_slot_goes_to_the_key_holding_the_fewest():
    slots = FairSlots(3)
    assert slots.per_owner == 2
    assert slots.acquire("a", 0) and slots.acquire("a", 0)
    assert not slots.acquire("a", 0)  # the last slot is left to the other keys
    assert slots.acquire("b", 0)
    got: list[str] = []
    waiters = [threading.Thread(target=lambda o=o: slots.acquire(o, 10) and got.append(o)) for o in ("a", "c")]
    for w in waiters:  # "a" waits first, but holds two slots; "c" holds none
        w.start()
        time.sleep(0.1)
    slots.release("b")
    time.sleep(0.2)
    assert got == ["c"]
    slots.release("a")
    waiters[0].join(5)
    assert got == ["c", "a"] and slots.held() == 3
