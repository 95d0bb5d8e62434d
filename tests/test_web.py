"""The page's routes over real HTTP: index, static files, three.js from node_modules, config; no path tricks.

The page's behaviour in a real browser is ``test_web_browser.py``.  Needs ``service/web/node_modules``
(``make test`` runs ``npm ci`` there first).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import httpx
import pytest
from test_preview import served, settings_for

from fastmesh.faces.facecount import TOLERANCE
from service.processes import local_redis
from service.web.routes import THREE_DIR, WEB_DIR

# Static `import ... from 'x'` / `export ... from 'x'` and dynamic `import('x')` specifiers.
IMPORT_RE = r"""(?:^|\n)\s*(?:import|export)\b[^'"]*?from\s*['"]([^'"]+)['"]|import\(\s*['"]([^'"]+)['"]\s*\)"""
DB = int(os.environ.get("FASTMESH_TEST_WEB_REDIS_DB", "9"))


@pytest.fixture(scope="module")
def client():
    url, server = local_redis(DB)
    s = settings_for(url, "routes", api_keys=["k1"], max_upload_bytes=123456, default_formats=["glb", "obj"])
    with served(s) as app:
        yield httpx.Client(base_url=app.url)
    if server:
        server.stop()


def test_index_is_public_and_imports_three_from_the_server(client):
    r = client.get("/")  # no API key: the page itself is public
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    importmap = json.loads(re.search(r'<script type="importmap">(.*?)</script>', r.text, re.S).group(1))
    assert importmap["imports"]["three"] == "/web/three/build/three.module.js"
    assert importmap["imports"]["three/addons/"] == "/web/three/examples/jsm/"
    assert "//" not in "".join(re.findall(r'(?:src|href)="([^"]+)"', r.text)).replace("/docs", "")  # no CDN


def test_every_module_the_page_imports_is_served(client):
    """Follow the import graph from app.js, as the browser would, resolving 'three' via the import map."""
    seen, todo = set(), ["/web/static/app.js"]
    while todo:
        path = todo.pop()
        if path in seen:
            continue
        seen.add(path)
        r = client.get(path)
        assert r.status_code == 200, path
        assert r.headers["content-type"].startswith("text/javascript"), path
        for spec in re.findall(IMPORT_RE, r.text):
            spec = spec[0] or spec[1]
            if spec == "three":
                todo.append("/web/three/build/three.module.js")
            elif spec.startswith("three/addons/"):
                todo.append("/web/three/examples/jsm/" + spec[len("three/addons/"):])
            else:
                todo.append(os.path.normpath(os.path.join(os.path.dirname(path), spec)))
    assert {"/web/static/viewer.js", "/web/three/build/three.module.js", "/web/three/build/three.core.js",
            "/web/three/examples/jsm/controls/OrbitControls.js",
            "/web/three/examples/jsm/loaders/GLTFLoader.js"} <= seen


def test_config_tells_the_page_defaults_limits_and_auth(client):
    cfg = client.get("/web/config.json").json()
    assert cfg["auth"] is True
    assert cfg["max_upload_bytes"] == 123456
    assert cfg["default_formats"] == ["glb", "obj"]
    assert set(cfg["formats"]) == {"glb", "obj", "ply"}
    assert {"seed", "temperature", "top_k", "top_p", "max_vertices", "enhancer", "filtering"} <= set(cfg["defaults"])
    assert cfg["bounds"]["top_k"] == {"min": 0, "max": 1_000_000}  # the API's own bounds (params.BOUNDS)
    assert cfg["bounds"]["temperature"]["min"] == 0 and cfg["bounds"]["candidates"] == {"min": 1, "max": 16}
    assert cfg["three_installed"] is True
    assert cfg["face_tolerance"] == TOLERANCE  # the page words target_met with the server's own tolerance
    assert "k1" not in json.dumps(cfg)


@pytest.mark.parametrize("path", [
    "/web/static/%2e%2e/routes.py",          # out of static/
    "/web/static/..%2froutes.py",
    "/web/static/nope.js",
    "/web/static/",                          # a directory
    "/web/three/package.json",               # three's own files outside build/ and examples/jsm/
    "/web/three/build/%2e%2e/package.json",
    "/web/three/src/Three.js",
    "/web/three/examples/jsm/%2e%2e/%2e%2e/package.json",
])
def test_nothing_outside_the_served_folders_leaks(client, path):
    r = client.get(path)
    assert r.status_code == 404, path
    assert r.json()["error"]["code"] == "not_found"


def test_node_modules_is_ignored_by_git_and_three_is_pinned():
    assert (WEB_DIR / ".gitignore").read_text().split() == ["node_modules/"]
    pinned = json.loads((WEB_DIR / "package.json").read_text())["dependencies"]["three"]
    assert re.fullmatch(r"\d+\.\d+\.\d+", pinned), "pin an exact version"
    lock = json.loads((WEB_DIR / "package-lock.json").read_text())
    assert lock["packages"]["node_modules/three"]["version"] == pinned
    installed = json.loads((Path(THREE_DIR) / "package.json").read_text())["version"]
    assert installed == pinned, "service/web/node_modules is stale: run `make web`"


def run_facts(function: str, calls: list[list]) -> list:
    """``function`` of the page's facts.js applied to each of ``calls`` (argument lists), in node: the page's own
    module, run without a browser."""
    node = shutil.which("node")
    assert node, "node missing: it comes with npm, which `make web` needs"
    script = (f"import {{ {function} }} from {json.dumps((WEB_DIR / 'static' / 'facts.js').as_uri())};"
              f"const calls = JSON.parse(process.argv[1]);"
              f"console.log(JSON.stringify(calls.map((args) => {function}(...args))));")
    out = subprocess.run([node, "--input-type=module", "-e", script, json.dumps(calls)], capture_output=True,
                         text=True, timeout=60, check=True)
    assert out.stderr == ""
    return json.loads(out.stdout)


def test_the_page_shows_faces_achieved_over_target_and_whether_it_holds():
    def result(faces, target=None, met=None):
        return {"faces": faces, "quality": {"faces": faces, "target_faces": target, "target_met": met}}

    got = run_facts("faceCount", [
        [result(812, 1000, True), TOLERANCE],
        [result(1246, 2000, False), TOLERANCE],
        [result(500, 500, True), 0.1],          # the tolerance as the server states it
        [result(148), TOLERANCE],               # no count asked for: the faces alone
        [{"faces": 7}, TOLERANCE],              # an older job without a quality report
        [result(300, 1000, False), None],       # a server that does not state its tolerance
        [{}, TOLERANCE],                        # no result yet
    ])
    assert got == ["812 / 1000 (within ±20 %)", "1246 / 2000 (outside ±20 %)", "500 / 500 (within ±10 %)", "148",
                   "7", "300 / 1000 (outside the tolerance)", None]
