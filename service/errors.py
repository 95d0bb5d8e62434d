"""Every error leaves the API as JSON ``{"error": {"code", "message"}}`` with a meaningful status.

Installed handlers cover our own :class:`ApiError`, Starlette's 404/405, FastAPI's request
validation (422), Redis outages (503) and, as a last resort, anything else (500, logged).
"""

from __future__ import annotations

import json
import logging

import redis
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

log = logging.getLogger("fastmesh.service")

HTTP_CODES = {400: "bad_request", 401: "unauthorized", 403: "forbidden", 404: "not_found",
              405: "method_not_allowed", 406: "not_acceptable", 409: "conflict", 413: "too_large",
              415: "unsupported_format", 422: "invalid_parameter", 429: "rate_limited",
              503: "unavailable"}

# ShapeError.code (fastmesh.shapes.io) -> HTTP status of the answer.
SHAPE_STATUS = {"unsupported_format": 415, "too_large": 413}


class ApiError(Exception):
    """An error answer: ``raise ApiError(404, "not_found", "no job 'x'")``."""

    def __init__(self, status: int, code: str, message: str, headers: dict[str, str] | None = None):
        super().__init__(message)
        self.status, self.code, self.message, self.headers = status, code, message, headers


def error_body(code: str, message: str) -> bytes:
    """The JSON body of every error answer, for the layers below FastAPI (ASGI middleware, the HTTP protocol)."""
    return json.dumps({"error": {"code": code, "message": message}}).encode()


def error_response(status: int, code: str, message: str, headers: dict | None = None) -> JSONResponse:
    return JSONResponse({"error": {"code": code, "message": message}}, status_code=status, headers=headers)


def _field(loc) -> str:
    # ('body', 'seed') -> 'seed'; ('query', 'format') -> 'format'
    parts = [str(p) for p in loc if p not in ("body", "query", "path", "header", "form")]
    return ".".join(parts) or "request"


def _given(error: dict) -> str:
    """", got 'x'" for a value outside a field's choices (a string field's, up to 30 characters), else ""."""
    if error.get("type") != "literal_error" or not isinstance(error.get("input"), str):
        return ""
    return f", got {error['input'][:30]!r}"


def install(app: FastAPI) -> None:
    @app.exception_handler(ApiError)
    async def _api(request: Request, exc: ApiError):
        return error_response(exc.status, exc.code, exc.message, exc.headers)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException):
        code = HTTP_CODES.get(exc.status_code, f"http_{exc.status_code}")
        message = exc.detail if isinstance(exc.detail, str) else str(exc.detail)
        if exc.status_code == 404 and message == "Not Found":
            message = f"no route {request.method} {request.url.path}"
        elif exc.status_code == 405:
            message = f"method {request.method} not allowed on {request.url.path}"
        return error_response(exc.status_code, code, message, getattr(exc, "headers", None))

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError):
        errs = exc.errors()
        message = "; ".join(f"{_field(e.get('loc', ()))}: {e.get('msg', 'invalid')}{_given(e)}" for e in errs[:5])
        return error_response(422, "invalid_parameter", message or "invalid request")

    @app.exception_handler(redis.RedisError)
    async def _redis(request: Request, exc: redis.RedisError):
        log.error("redis error on %s %s: %s", request.method, request.url.path, exc)
        why = "full (its memory cap is reached)" if isinstance(exc, redis.exceptions.OutOfMemoryError) \
            else "unreachable"
        return error_response(503, "unavailable", f"the job store (Redis) is {why}; retry later",
                              {"Retry-After": "5"})

    @app.exception_handler(Exception)
    async def _any(request: Request, exc: Exception):
        log.exception("unhandled error on %s %s", request.method, request.url.path)
        return error_response(500, "internal", f"internal error ({type(exc).__name__}); it has been logged")
