"""The browser page: ``/`` (index.html), its static files, three.js from node_modules, and the page's config.

No bundler and no build step: the page is plain ES modules; an import map in index.html points
``three`` and ``three/addons/`` at :data:`THREE_PREFIX`, which serves the ``build/`` and
``examples/jsm/`` folders of the three.js npm package pinned in ``service/web/package.json``
(installed into ``service/web/node_modules`` by ``make run`` / ``make test``; never committed).

Everything here is public (no API key): it is the same for every visitor.  The page sends the
key it is given to the ``/v1`` endpoints as ``Authorization: Bearer``.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import FileResponse, JSONResponse, Response

from fastmesh.faces.facecount import TOLERANCE
from fastmesh.params import BOUNDS, PARAMETERS
from fastmesh.shapes.shape import EXPORT_FORMATS, SUPPORTED_FORMATS
from fastmesh_jobs.settings import Settings

from ..errors import ApiError

WEB_DIR = Path(__file__).resolve().parent
STATIC_DIR = WEB_DIR / "static"
THREE_DIR = WEB_DIR / "node_modules" / "three"
STATIC_PREFIX = "/web/static"
THREE_PREFIX = "/web/three"
# Only these subtrees of the three package are reachable (no package.json, src/, docs...).
THREE_SUBTREES = ("build/", "examples/jsm/")
SERVED_TYPES = {".js": "text/javascript", ".css": "text/css", ".html": "text/html", ".svg": "image/svg+xml",
                ".json": "application/json", ".wasm": "application/wasm"}
# The page's own files change with deployments: revalidate.  three.js is pinned by version in its path's
# package, but the URL carries no version, so it is cached for a day only.
STATIC_CACHE = "no-cache"
THREE_CACHE = "public, max-age=86400"


def _file(root: Path, rel: str, cache: str) -> FileResponse:
    """``root/rel`` if it is a file inside ``root`` with a served type, else a JSON 404 (no path tricks)."""
    try:
        path = (root / rel).resolve()
        inside = path.is_relative_to(root.resolve()) and path.is_file()
    except (OSError, ValueError):
        inside = False
    media = SERVED_TYPES.get(path.suffix.lower()) if inside else None
    if media is None:
        raise ApiError(404, "not_found", f"no file '{rel[:200]}'")
    return FileResponse(path, media_type=media, headers={"Cache-Control": cache})


def page_params() -> list[dict]:
    """The generation parameters the page makes its inputs of (``static/inputs.js``), in the order of
    ``GenerateParams``: name, type (int, float, bool or choice), choices, help (with what an empty input does)."""
    return [{"name": prm.name, "type": "choice" if prm.choices else prm.type.__name__, "choices": list(prm.choices),
             "help": f"{prm.help}; empty = {prm.unset}" if prm.unset else prm.help} for prm in PARAMETERS]


def page_config(settings: Settings, defaults: dict) -> dict:
    """What the page needs to know to build its form and word the result: the parameters, their defaults and
    limits, formats, auth, and the share of ``target_faces`` a result's face count may miss it by
    (``target_met``)."""
    return {
        "auth": bool(settings.api_keys),
        "params": page_params(),
        "defaults": defaults,
        # The input fields' min/max, from the bounds the API validates with (0 where 0 switches a feature off).
        "bounds": {name: {"min": 0 if b.zero else b.lo, "max": b.hi} for name, b in BOUNDS.items()},
        "default_formats": list(settings.default_formats),
        "formats": list(EXPORT_FORMATS),
        "input_formats": list(SUPPORTED_FORMATS),
        "max_upload_bytes": settings.max_upload_bytes,
        "max_points": settings.max_points,
        "face_tolerance": TOLERANCE,
    }


def web_router(settings: Settings, defaults: dict) -> APIRouter:
    """Routes of the page.  ``defaults`` are the generation defaults the API applies to omitted fields."""
    router = APIRouter(include_in_schema=False)
    config = page_config(settings, defaults)

    @router.get("/")
    def index() -> FileResponse:
        return _file(STATIC_DIR, "index.html", STATIC_CACHE)

    @router.get("/favicon.ico")
    def favicon() -> Response:
        return Response(status_code=204)  # no icon; keeps browsers' automatic request out of the 404 logs

    @router.get("/web/config.json")
    def web_config() -> JSONResponse:
        return JSONResponse({**config, "three_installed": (THREE_DIR / "build" / "three.module.js").is_file()},
                            headers={"Cache-Control": "no-cache"})

    @router.get(STATIC_PREFIX + "/{rel:path}")
    def static(rel: str) -> FileResponse:
        return _file(STATIC_DIR, rel, STATIC_CACHE)

    @router.get(THREE_PREFIX + "/{rel:path}")
    def three(rel: str) -> FileResponse:
        subtree = next((s for s in THREE_SUBTREES if rel.startswith(s)), None)
        if subtree is None:
            raise ApiError(404, "not_found", f"no file '{rel[:200]}'")
        if not THREE_DIR.is_dir():
            raise ApiError(503, "three_missing", "three.js is not installed: run `make run` (or "
                                                 "`npm ci --prefix service/web`)")
        # Containment is checked against the subtree itself: 'build/../package.json' must not escape it.
        return _file(THREE_DIR / subtree, rel[len(subtree):], THREE_CACHE)

    return router
