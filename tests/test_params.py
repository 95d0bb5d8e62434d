"""Each generation parameter is declared once (``fastmesh.params.GenerateParams`` with ``BOUNDS`` / ``CHOICES``)
and is, from that declaration alone, a form field of the service (its range in the OpenAPI schema), a flag of
``generate``, ``submit`` and ``loadtest``, and an input of the web page.  Every check walks
``fields(GenerateParams)``: a field added there that an interface misses fails here.

No Redis, no worker: the app's schema is built without serving, the form dependency runs in a bare app.
"""

from __future__ import annotations

import asyncio
import json
import shutil
import subprocess
from dataclasses import fields

import httpx
import pytest
from fastapi import Depends, FastAPI

from fastmesh.cli import build_parser
from fastmesh.cli.flags import given_params, params_from_args
from fastmesh.params import BOUNDS, CHOICES, PARAMETERS, GenerateParams
from fastmesh_jobs.settings import Settings
from service.app import create_app
from service.routes.form import FormFields, form_fields
from service.web.routes import STATIC_DIR, page_config

NAMES = [f.name for f in fields(GenerateParams)]
SCHEMA_TYPES = {int: "integer", float: "number", bool: "boolean", str: "string"}


def other_value(name: str):
    """A valid value of ``name`` other than its default, as Python and as typed on a command line or form."""
    default = getattr(GenerateParams(), name)
    if name in CHOICES:
        value = next(c for c in CHOICES[name] if c != default)
    elif isinstance(default, bool):
        value = not default
    elif name in BOUNDS:
        b = BOUNDS[name]
        value = int(b.lo) + 1 if b.integer else min(b.hi, b.lo * 2 + 0.5)
    else:
        raise AssertionError(f"{name}: no BOUNDS or CHOICES entry, and not a bool")
    return value


def test_parameters_follow_the_dataclass():
    assert [p.name for p in PARAMETERS] == NAMES
    for prm in PARAMETERS:
        assert prm.help and prm.type in SCHEMA_TYPES, prm.name
        assert (prm.type is str) == bool(prm.choices), f"{prm.name}: a string parameter takes CHOICES"
        assert prm.type in (bool, str) or prm.bound is not None, f"{prm.name}: a number parameter has BOUNDS"
        assert prm.default is not None or prm.unset, f"{prm.name}: say what None does (unset=...)"


@pytest.fixture(scope="module")
def form_schema() -> dict:
    spec = create_app(Settings(redis_url="redis://127.0.0.1:6379/0")).openapi()  # building it connects nowhere
    for route in ("/v1/jobs", "/v1/batches"):
        body = next(iter(spec["paths"][route]["post"]["requestBody"]["content"].values()))["schema"]
        assert body["$ref"]
    ref = body["$ref"].rsplit("/", 1)[1]
    return spec["components"]["schemas"][ref]["properties"]


@pytest.mark.parametrize("name", NAMES)
def test_each_parameter_is_a_form_field_with_its_range(form_schema, name):
    prm = next(p for p in PARAMETERS if p.name == name)
    field = form_schema[name]
    schema = next(s for s in field["anyOf"] if s.get("type") != "null")  # None: the default
    assert schema["type"] == SCHEMA_TYPES[prm.type]
    if name in BOUNDS:
        b = BOUNDS[name]
        low = "exclusiveMinimum" if b.lo_open and not b.zero else "minimum"
        assert schema[low] == (0 if b.zero else b.lo) and schema["maximum"] == float(b.hi)  # JSON: a float
    if name in CHOICES:
        assert schema["enum"] == list(CHOICES[name])
    assert prm.help.split(",")[0].lower() in field["description"].lower()


def post(app: FastAPI, data: dict) -> httpx.Response:
    async def call():
        async with httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://app") as client:
            return await client.post("/f", data=data)

    return asyncio.run(call())


def test_the_form_dependency_hands_every_parameter_on():
    app = FastAPI()

    @app.post("/f")
    async def echo(form: FormFields = Depends(form_fields)) -> dict:
        return {"generation": form.generation, "formats": form.formats}

    sent = {name: other_value(name) for name in NAMES}
    wire = {k: str(v).lower() if isinstance(v, bool) else str(v) for k, v in sent.items()}
    r = post(app, {**wire, "formats": "obj"})
    assert r.status_code == 200, r.text
    assert r.json() == {"generation": sent, "formats": "obj"}
    assert post(app, {}).json()["generation"] == dict.fromkeys(NAMES)


def _flags(name: str, value) -> list[str]:
    prm = next(p for p in PARAMETERS if p.name == name)
    if isinstance(value, bool):
        return [prm.flag if value else "--no-" + prm.flag[2:]]
    return [prm.flag, str(value)]


@pytest.mark.parametrize("verb,head", [("generate", ["in.ply", "-o", "out.glb"]),
                                       ("submit", ["in.ply", "--url", "http://x"]),
                                       ("loadtest", ["--url", "http://x", "--inputs", "d"])])
def test_each_parameter_is_a_flag(verb, head):
    parser = build_parser()
    unset = parser.parse_args([verb, *head])
    if verb == "generate":  # the library's defaults; submit and loadtest leave them to the service
        assert params_from_args(unset) == GenerateParams()
    else:
        assert given_params(unset) == {}
    sent = {name: other_value(name) for name in NAMES}
    args = parser.parse_args([verb, *head, *[a for n, v in sent.items() for a in _flags(n, v)]])
    assert given_params(args) == sent
    assert params_from_args(args) == GenerateParams(**sent)


def test_eval_takes_the_generation_flags_but_not_the_outputs():
    args = build_parser().parse_args(["eval", "--inputs", "i", "--reference", "r", "--target-faces", "300"])
    assert params_from_args(args).target_faces == 300
    assert set(given_params(args)) == {p.name for p in PARAMETERS if not p.output and p.default is not None} | {
        "target_faces"}


def test_each_parameter_is_an_input_of_the_web_page():
    params = page_config(Settings(redis_url="redis://127.0.0.1:6379/0"), {})["params"]
    assert [p["name"] for p in params] == NAMES
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed: the page's inputs are made by static/inputs.js")
    script = (f"import('{(STATIC_DIR / 'inputs.js').as_uri()}').then((m) => "
              f"console.log(m.inputsHtml({json.dumps(params)})))")
    html = subprocess.run([node, "--input-type=module", "-e", script], capture_output=True, text=True,
                          check=True).stdout
    for prm in PARAMETERS:
        if prm.type is bool:
            assert f'<input name="{prm.name}" type="checkbox">' in html, prm.name
        elif prm.choices:
            options = "".join(f'<option value="{c}">{c}</option>' for c in prm.choices)
            assert f'<select name="{prm.name}">{options}</select>' in html, prm.name
        else:
            step = "1" if prm.type is int else "any"
            assert f'<input name="{prm.name}" type="number" step="{step}">' in html, prm.name
