"""The page in a real headless Chromium (Debian's, driven by playwright) against the real stack.

Real parts: Redis (database ``FASTMESH_TEST_WEB_REDIS_DB``, default 12; keys unique to the run, deleted after),
the API served by uvicorn, a ``fastmesh-worker`` subprocess with a tiny random model, three.js from
``service/web/node_modules`` and WebGL in Chromium's software renderer.  ``make test`` installs
chromium (scripts/install-chromium.sh) and three.js (scripts/install-web.sh) first.

Set ``FASTMESH_WEB_SHOTS=DIR`` to keep the screenshots the tests take.
"""

from __future__ import annotations

import io
import os
import tempfile
from pathlib import Path

import httpx
import numpy as np
import pytest
import trimesh
from test_preview import served, settings_for

from service.processes import WorkerProcess, local_redis

DB = int(os.environ.get("FASTMESH_TEST_WEB_REDIS_DB", "9"))
CHROMIUM = os.environ.get("FASTMESH_CHROMIUM", "/usr/bin/chromium")
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]
# Progress written often (the page shows it); heartbeats left at their defaults: on a loaded machine a short
# heartbeat TTL gets a busy worker's job requeued, which is the worker tests' subject, not this one's.
FAST = dict(progress_interval=0.05)
JOB_TIMEOUT_MS = 120_000  # waiting for a job in the page; the tiny model takes seconds

# Reads the WebGL canvas back (it keeps its drawing buffer) and summarises it: how much of it is not the
# clear colour, how many distinct colours (flat shading gives several), and dark / orange pixels
# (wireframe lines / input points).
CANVAS_STATS = """() => {
  // Drawn now, in this task: a WebGL canvas read after its frame was shown can give an older or cleared buffer.
  fastmesh.viewer.render();
  const c = document.querySelector('#viewer canvas');
  const t = document.createElement('canvas');
  t.width = c.width; t.height = c.height;
  const ctx = t.getContext('2d');
  ctx.drawImage(c, 0, 0);
  const d = ctx.getImageData(0, 0, t.width, t.height).data;
  let covered = 0, dark = 0, orange = 0;
  const colors = new Set();
  for (let i = 0; i < d.length; i += 4) {
    const [r, g, b] = [d[i], d[i + 1], d[i + 2]];
    if (Math.abs(r - 0xf4) + Math.abs(g - 0xf5) + Math.abs(b - 0xf8) > 24) {
      covered++;
      colors.add(((r >> 3) << 10) | ((g >> 3) << 5) | (b >> 3));
    }
    if (r + g + b < 300) dark++;
    if (r > 170 && g < 150 && b < 110 && r - b > 90) orange++;
  }
  const n = d.length / 4;
  return {covered: covered / n, colors: colors.size, dark, orange, width: t.width, height: t.height};
}"""

# Records every status the page shows, so a test can tell what the user saw along the way.
WATCH_STATUS = """() => {
  window.__statuses = [];
  const el = document.querySelector('#status');
  new MutationObserver(() => {
    const s = el.textContent;
    if (window.__statuses[window.__statuses.length - 1] !== s) window.__statuses.push(s);
  }).observe(el, {childList: true, characterData: true, subtree: true});
}"""


def ascii_ply(p: np.ndarray) -> bytes:
    """Points ``(n, 3)`` as an ASCII PLY (what a scanner might give)."""
    header = (f"ply\nformat ascii 1.0\nelement vertex {len(p)}\n"
              "property float x\nproperty float y\nproperty float z\nend_header\n")
    body = io.StringIO()
    np.savetxt(body, p, fmt="%.5f")
    return header.encode() + body.getvalue().encode()


def box_cloud(n: int = 1500) -> bytes:
    """Points on the surface of an off-origin box: flat-sided, so rebuilt from its planes without the networks."""
    rng = np.random.default_rng(3)
    p = rng.uniform(-1, 1, size=(n, 3))
    axis = rng.integers(0, 3, n)
    p[np.arange(n), axis] = np.sign(p[np.arange(n), axis])
    return ascii_ply(p * [1.0, 0.6, 0.4] + [2.0, 1.0, -1.0])


def pebble_cloud(n: int = 1500) -> bytes:
    """Points on an off-origin ellipsoid: curved, so the networks decode it (every stage runs and reports)."""
    p = np.random.default_rng(3).normal(size=(n, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    return ascii_ply(p * [1.0, 0.6, 0.4] + [2.0, 1.0, -1.0])


@pytest.fixture(scope="module")
def redis_url():
    url, server = local_redis(DB)
    yield url
    if server:
        server.stop()


@pytest.fixture(scope="module")
def stack(redis_url, weights, tmp_path_factory):
    """An open API (no keys) with one real worker."""
    # Each progress call sleeps 0.3 s: a decoded job reports about ten times, so it runs for seconds and the page,
    # polling every 0.4 s, sees it running (a box rebuilt from its planes reports once).
    s = settings_for(redis_url, "browser", weights=weights, debug_step_delay=0.3, **FAST)
    with served(s) as app:
        worker = WorkerProcess(s, s.queue_name + "-w1", tmp_path_factory.mktemp("logs") / "worker.log")
        try:
            worker.wait_ready()
            yield app
        finally:
            worker.stop()
            print(f"worker log ({worker.log_path}):\n{worker.log()[-4000:]}")


@pytest.fixture(scope="module")
def browser():
    from playwright.sync_api import sync_playwright

    assert Path(CHROMIUM).exists(), f"{CHROMIUM} missing: run `make chromium` (Debian's chromium)"
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, headless=True)
        yield b
        b.close()


@pytest.fixture(scope="module")
def shot_dir():
    d = Path(os.environ.get("FASTMESH_WEB_SHOTS") or tempfile.mkdtemp(prefix="fastmesh-shots-"))
    d.mkdir(parents=True, exist_ok=True)
    return d


@pytest.fixture
def page(browser, shot_dir, request):
    context = browser.new_context(viewport={"width": 1100, "height": 800}, accept_downloads=True)
    pg = context.new_page()
    errors: list[str] = []
    pg.on("pageerror", lambda e: errors.append(str(e)))
    # Shown by pytest when the test fails: what the page said, and where its last screenshot is.
    pg.on("console", lambda m: print(f"[console.{m.type}] {m.text}"))
    pg.on("requestfailed", lambda r: print(f"[request failed] {r.method} {r.url}: {r.failure}"))
    pg.on("response", lambda r: r.status >= 400 and print(f"[response] {r.status} {r.request.method} {r.url}"))
    yield pg
    last = shot_dir / f"{request.node.name}-last.png"
    pg.screenshot(path=str(last))
    print(f"last screenshot: {last}")
    context.close()
    assert not errors, f"JavaScript errors on the page: {errors}"


@pytest.fixture
def shots(request, shot_dir):
    return lambda page, name: page.screenshot(path=str(shot_dir / f"{request.node.name}-{name}.png"))


def open_page(page, url: str) -> None:
    page.goto(url + "/")
    page.wait_for_selector("body[data-ready='1']")


def choose(page, tmp_path: Path, name: str, data: bytes) -> None:
    f = tmp_path / name
    f.write_bytes(data)
    page.set_input_files("#file", str(f))


def test_from_a_point_cloud_to_a_downloaded_glb(stack, page, tmp_path, shots):
    open_page(page, stack.url)
    # The defaults the server applies are shown in the form.
    defaults = httpx.get(stack.url + "/web/config.json").json()["defaults"]
    assert page.input_value("input[name=top_p]") == str(defaults["top_p"])
    choose(page, tmp_path, "pebble.ply", pebble_cloud())
    page.fill("input[name=seed]", "7")
    # A random model joins a few vertices into many overlapping faces (every triple of them): keep it small,
    # as software WebGL and the server's preview fill every one of them.
    page.fill("input[name=max_vertices]", "12")
    page.evaluate(WATCH_STATUS)
    page.click("#submit")
    page.wait_for_selector("#status.succeeded", timeout=JOB_TIMEOUT_MS)
    job_id = page.evaluate("location.hash").removeprefix("#job=")
    job = httpx.get(f"{stack.url}/v1/jobs/{job_id}").json()
    assert job["status"] == "succeeded" and job["params"]["seed"] == 7 and job["params"]["max_vertices"] == 12
    seen = page.evaluate("window.__statuses")
    assert seen[-1] == "succeeded" and "running" in seen, seen
    assert set(seen) <= {"idle", "queued", "running", "succeeded"}, seen

    # Counts and timings as the API reports them; the 3D view holds the same mesh.
    assert page.text_content("#c-vertices") == str(job["result"]["vertices"])
    assert page.text_content("#c-faces") == str(job["result"]["faces"])
    assert page.text_content("#c-input") == "1500 points"
    # The quality report beside the counts, as the API gives it.
    q = job["result"]["quality"]
    assert page.text_content("#c-distance") == f"{q['cd']:.2f} % / {q['hd']:.2f} %"
    assert page.text_content("#c-boundary") == str(q["boundary_edges"])
    assert page.text_content("#c-non-manifold") == str(q["non_manifold_edges"])
    assert page.text_content("#c-components") == str(q["components"])
    assert page.text_content("#c-watertight") == ("yes" if q["watertight"] else "no")
    assert page.locator("#timings tbody tr").count() >= 5
    page.wait_for_function("document.querySelector('#viewer').dataset.faces !== undefined")
    assert page.get_attribute("#viewer", "data-faces") == str(job["result"]["faces"])
    assert page.locator("#viewer canvas").count() == 1  # one WebGL context, however many polls it took

    # The canvas drew a shaded mesh with its wireframe and the input points over it (the points arrive on
    # their own request, which a loaded machine can answer after the mesh's).
    page.wait_for_function("fastmesh.viewer.points !== null && !fastmesh.viewer.frameRequested",
                           timeout=JOB_TIMEOUT_MS)
    with_all = page.evaluate(CANVAS_STATS)
    shots(page, "result")
    assert with_all["covered"] > 0.03 and with_all["colors"] >= 4, with_all
    assert with_all["orange"] > 100, with_all
    page.uncheck("#wireframe")
    no_wire = page.evaluate(CANVAS_STATS)
    assert no_wire["dark"] < with_all["dark"], (no_wire, with_all)
    page.uncheck("#points")
    no_points = page.evaluate(CANVAS_STATS)
    assert no_points["orange"] < with_all["orange"] / 10 and no_points["covered"] > 0.01, no_points
    shots(page, "plain")
    # Orbiting changes the picture (OrbitControls re-renders on demand).
    box = page.locator("#viewer canvas").bounding_box()
    page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    page.mouse.down()
    page.mouse.move(box["x"] + box["width"] / 2 + 150, box["y"] + box["height"] / 2 + 40, steps=5)
    page.mouse.up()
    page.wait_for_function("!fastmesh.viewer.frameRequested")
    assert page.evaluate(CANVAS_STATS) != no_points

    # The GLB button downloads the job's mesh, named after the input.
    with page.expect_download() as dl:
        page.click("#dl-glb")
    assert dl.value.suggested_filename == "pebble.glb"
    path = tmp_path / "out.glb"
    dl.value.save_as(path)
    mesh = trimesh.load(path, force="mesh")
    assert len(mesh.faces) == job["result"]["faces"] and len(mesh.vertices) > 0
    with page.expect_download() as dl:
        page.click("#dl-obj")
    assert dl.value.suggested_filename == "pebble.obj"
    assert len(trimesh.load(dl.value.path(), file_type="obj", force="mesh").faces) == job["result"]["faces"]
    with page.expect_download() as dl:
        page.click("#dl-png")  # the server-side preview, as drawn with the wireframe off (as toggled)
    assert dl.value.suggested_filename == "pebble-preview.png"
    assert Path(dl.value.path()).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    # The job is remembered by this browser, and a reload shows it again.
    assert page.locator("#recent li").count() == 1
    assert "pebble.ply" in page.text_content("#recent li") and "succeeded" in page.text_content("#recent li")
    page.reload()
    page.wait_for_selector("#status.succeeded", timeout=JOB_TIMEOUT_MS)
    assert page.text_content("#c-faces") == str(job["result"]["faces"])
    assert page.locator("#recent li").count() == 1

    # A refused submission next: the error stands alone, the previous mesh, badge and counts are gone.
    page.wait_for_function("document.querySelector('#viewer').dataset.faces !== undefined")
    choose(page, tmp_path, "broken.ply", b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n")
    page.click("#submit")
    page.wait_for_selector("#error:not([hidden])")
    assert page.text_content("#error").startswith("Invalid input: ")
    assert page.get_attribute("#status", "class") == "badge idle" and page.text_content("#status") == "idle"
    for cell in ("#c-vertices", "#c-faces", "#c-distance", "#c-watertight"):
        assert page.text_content(cell) == "-", cell
    assert page.get_attribute("#viewer", "data-faces") is None and page.evaluate("fastmesh.viewer.mesh") is None
    assert page.evaluate(CANVAS_STATS)["covered"] < 0.001  # nothing drawn: neither mesh nor input points
    assert "refused" in page.text_content("#viewer-note") and page.evaluate("location.hash") == ""
    assert page.locator("#timings tbody tr").count() == 0 and page.is_disabled("#dl-glb")
    shots(page, "error-after-result")
    page.click("#recent li a")  # the earlier job is still one click away
    page.wait_for_selector("#status.succeeded", timeout=JOB_TIMEOUT_MS)
    assert page.text_content("#c-faces") == str(job["result"]["faces"])


def test_a_corrupt_file_shows_the_servers_message(stack, page, tmp_path, shots):
    open_page(page, stack.url)
    junk = b"ply\nformat binary_little_endian 1.0\nelement vertex 100\nproperty float x\nend_header\n\x00\x01"
    expected = httpx.post(stack.url + "/v1/jobs", files={"file": ("broken.ply", junk)})
    assert expected.status_code == 422
    choose(page, tmp_path, "broken.ply", junk)
    page.click("#submit")
    page.wait_for_selector("#error:not([hidden])")
    text = page.text_content("#error")
    shots(page, "error")
    assert text.startswith("Invalid input: ")
    assert expected.json()["error"]["message"] in text
    assert page.locator("#recent li").count() == 0  # nothing was created

    choose(page, tmp_path, "notes.docx", b"PK\x03\x04 not a mesh")
    page.click("#submit")
    page.wait_for_function("document.querySelector('#error').textContent.startsWith('Unsupported file format')")


def test_keys_queue_position_queue_full_and_drop(redis_url, page, tmp_path, shots):
    """No worker: jobs stay queued.  Keys on, a queue of one."""
    s = settings_for(redis_url, "browser-keys", api_keys=["sesame"], max_queue_depth=1, max_upload_bytes=200_000,
                     **FAST)
    with served(s) as app:
        open_page(page, app.url)
        assert page.is_visible("#api-key")
        choose(page, tmp_path, "cloud.ply", box_cloud(300))
        page.click("#submit")
        page.wait_for_function("document.querySelector('#error').textContent.startsWith('API key needed')")

        page.fill("#api-key", "sesame")
        page.click("#key-form button")
        # Drop a file on the drop zone as a user would drag one from their desktop.
        page.evaluate("""(text) => {
          const dt = new DataTransfer();
          dt.items.add(new File([text], 'dropped.ply'));
          document.querySelector('#drop').dispatchEvent(new DragEvent('drop', {dataTransfer: dt, bubbles: true}));
        }""", box_cloud(300).decode())
        assert "dropped.ply" in page.text_content("#drop-text")
        page.click("#submit")
        page.wait_for_selector("#status.queued")
        assert page.text_content("#status-detail") == "next in line"
        assert page.is_hidden("#error")

        page.click("#submit")  # the queue holds one job: the second is refused
        page.wait_for_function("document.querySelector('#error').textContent.startsWith('Queue full')")
        assert "Try again in" in page.text_content("#error")
        shots(page, "queue-full")

        big = tmp_path / "big.xyz"
        big.write_bytes(b"0 0 0\n" * 40_000)  # 240 kB, over this server's 200 kB
        page.set_input_files("#file", str(big))
        page.click("#submit")
        page.wait_for_function("document.querySelector('#error').textContent.startsWith('File too large')")

        page.reload()  # the key stays in this browser
        page.wait_for_selector("body[data-ready='1']")
        assert page.input_value("#api-key") == "sesame"
        page.click("#recent li a")  # the refused submissions closed the queued job's view; it is remembered
        page.wait_for_selector("#status.queued")
        page.click("#cancel")
        page.wait_for_selector("#status.cancelled")
        assert page.is_hidden("#cancel")
        assert "cancelled" in page.text_content("#recent li")


def test_quads_uv_and_pivot_from_the_form(stack, page, tmp_path, shots):
    """topology, uv, origin, height and up are fields of the form; the page shows the quad share and the notes."""
    open_page(page, stack.url)
    assert page.input_value("select[name=topology]") == "triangle" and not page.is_checked("input[name=uv]")
    box = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    box.apply_translation([4.0, 1.0, -2.0])
    choose(page, tmp_path, "crate.obj", box.export(file_type="obj").encode())
    page.select_option("select[name=topology]", "quad")
    page.select_option("select[name=origin]", "bottom")
    page.select_option("select[name=up]", "z")
    page.fill("input[name=height]", "2")
    page.check("input[name=uv]")
    page.click("#submit")
    page.wait_for_selector("#status.succeeded", timeout=JOB_TIMEOUT_MS)
    job_id = page.evaluate("location.hash").removeprefix("#job=")
    job = httpx.get(f"{stack.url}/v1/jobs/{job_id}").json()
    assert {k: job["params"][k] for k in ("topology", "uv", "bake", "origin", "height", "up")} == {
        "topology": "quad", "uv": True, "bake": False, "origin": "bottom", "height": 2.0, "up": "z"}
    assert page.text_content("#c-quads") == "6 (100 % of the polygons)"
    assert "GLB holds triangles" in page.text_content("#c-notes")
    glb = httpx.get(f"{stack.url}/v1/jobs/{job_id}/result", params={"format": "glb"}).content
    mesh = trimesh.load(io.BytesIO(glb), file_type="glb", force="mesh", process=False)
    assert np.allclose(mesh.bounds, [[-0.5, 0, -1.5], [0.5, 2, 1.5]]) and mesh.visual.uv is not None
    shots(page, "quads")


def test_a_face_count_shows_achieved_over_target(stack, page, tmp_path, shots):
    """Asked for a face count, the page shows "achieved / target" and whether it holds, as the API reports it;
    without one, the faces alone (the first test)."""
    open_page(page, stack.url)
    choose(page, tmp_path, "crate.ply", box_cloud())
    page.fill("input[name=max_vertices]", "12")
    page.fill("input[name=target_faces]", "40")
    page.click("#submit")
    page.wait_for_selector("#status.succeeded", timeout=JOB_TIMEOUT_MS)
    job_id = page.evaluate("location.hash").removeprefix("#job=")
    result = httpx.get(f"{stack.url}/v1/jobs/{job_id}").json()["result"]
    q = result["quality"]
    assert q["target_faces"] == 40 and q["target_met"] is (abs(result["faces"] - 40) <= 8)
    held = "within" if q["target_met"] else "outside"
    assert page.text_content("#c-faces") == f"{result['faces']} / 40 ({held} ±20 %)"
    shots(page, "face-count")
