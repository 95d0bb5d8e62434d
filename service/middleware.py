"""ASGI middleware: the API-key gate, the upload size cap and request metrics.

All are plain ASGI (no BaseHTTPMiddleware) so they add microseconds, not a task per request.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import anyio
import redis
from starlette.datastructures import Headers
from starlette.middleware.cors import CORSMiddleware
from starlette.responses import Response

from .errors import error_body, error_response
from .telemetry import Metrics

GATED = ("/v1/", "/metrics")  # paths that need a key when keys are configured
# Room for the multipart framing and the small form fields around the file.
MULTIPART_OVERHEAD = 64 * 1024


def _json_error(status: int, code: str, message: str, headers: dict[str, str] | None = None) -> tuple[dict, dict]:
    body = error_body(code, message)
    start = {"type": "http.response.start", "status": status,
             "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                         (b"connection", b"close"), *((k.lower().encode(), v.encode()) for k, v in
                                                      (headers or {}).items())]}
    return start, {"type": "http.response.body", "body": body}


async def _answer(send, status: int, code: str, message: str, headers: dict[str, str] | None = None) -> None:
    start, body = _json_error(status, code, message, headers)
    await send(start)
    await send(body)


class ApiKeyGate:
    """Check the API key of every ``/v1/`` and ``/metrics`` request from its headers, before any of its body
    is read.

    ``owner_of(token)`` names the owner of a bearer token (None for no key).  Failed attempts are counted
    per client address (``fail_hit(address)`` -> seconds to wait, 0 = allowed, ``fail_wait(address)`` the
    same without counting); past the limit, requests from that address get 429 until the window ends,
    so keys cannot be guessed at line rate.  ``admit(address, owner)`` remembers a key that authenticated
    from an address while it was under the limit and says whether it did: such a key is never locked out
    by someone else's failures from the same address (a proxy, a NAT, docker's gateway), while a key first
    seen during the lockout waits like a guess, so the answer never tells a guesser that a key is right.
    Two ``Authorization`` headers are refused: which one counts would depend on the framework.
    """

    def __init__(self, app, owner_of: Callable[[str], str | None], fail_hit: Callable[[str], int],
                 fail_wait: Callable[[str], int], admit: Callable[[str, str], bool]):
        self.app, self.owner_of, self.fail_hit, self.fail_wait = app, owner_of, fail_hit, fail_wait
        self.admit = admit

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or not scope["path"].startswith(GATED) or scope["method"] == "OPTIONS":
            return await self.app(scope, receive, send)
        auth = [v for k, v in scope.get("headers", []) if k == b"authorization"]
        if len(auth) > 1:
            return await _answer(send, 400, "bad_request", "send one Authorization header, not several")
        address = (scope.get("client") or ("unknown",))[0]
        scheme, _, token = (auth[0].decode("latin-1") if auth else "").partition(" ")
        owner = self.owner_of(token.strip()) if scheme.lower() == "bearer" else None
        try:
            if owner is not None and await anyio.to_thread.run_sync(self.admit, address, owner):
                return await self.app(scope, receive, send)
            wait = await anyio.to_thread.run_sync(self.fail_wait, address)
            if not wait and owner is not None:  # the lockout's window ended in between
                return await self.app(scope, receive, send)
            if not wait:
                wait = await anyio.to_thread.run_sync(self.fail_hit, address)
        except redis.RedisError:
            return await _answer(send, 503, "unavailable", "the job store (Redis) is unreachable; retry later",
                                 {"Retry-After": "5"})
        if wait:
            return await _answer(send, 429, "rate_limited", "too many failed authentications from this address; "
                                                            "retry later", {"Retry-After": str(wait)})
        await _answer(send, 401, "unauthorized", "missing or unknown API key; send 'Authorization: Bearer <key>'",
                      {"WWW-Authenticate": "Bearer"})


class BodyLimit:
    """Answer 413 as soon as a request body exceeds ``max_bytes`` (+ multipart overhead), 408 when
    ``idle_seconds`` pass without any of it arriving or when it is not complete ``deadline_seconds`` after
    the request began (a slow client holds a connection and a worker thread otherwise).

    A declared Content-Length is checked before reading anything; a chunked body is counted as it
    arrives, and once over the limit the app sees a disconnect while the client gets the 413.
    """

    def __init__(self, app, max_bytes: int, idle_seconds: float = 30.0, deadline_seconds: float = 300.0):
        self.app, self.limit, self.idle = app, max_bytes + MULTIPART_OVERHEAD, idle_seconds
        self.deadline_seconds = deadline_seconds
        self.mib = max_bytes / (1024 * 1024)

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or scope["method"] not in ("POST", "PUT", "PATCH"):
            return await self.app(scope, receive, send)
        msg = f"upload larger than the {self.mib:g} MiB limit (max_upload_bytes)"
        for k, v in scope.get("headers", []):
            if k == b"content-length":
                try:
                    declared = int(v)
                except ValueError:
                    declared = -1
                if declared > self.limit:
                    return await _answer(send, 413, "too_large", msg)
        seen = 0
        answered = False
        deadline = time.monotonic() + self.deadline_seconds

        async def limited_receive():
            nonlocal seen, answered
            if answered:
                return {"type": "http.disconnect"}
            left = deadline - time.monotonic()
            with anyio.move_on_after(min(self.idle, max(0.0, left))) as waited:
                message = await receive()
            if waited.cancelled_caught:
                answered = True
                why = f"no part of the request body arrived for {self.idle:g} s (body_timeout_seconds)" \
                    if left > self.idle else \
                    f"the request body was not complete within {self.deadline_seconds:g} s (upload_deadline_seconds)"
                await _answer(send, 408, "timeout", why)
                return {"type": "http.disconnect"}
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > self.limit:
                    answered = True
                    start, body = _json_error(413, "too_large", msg)
                    await send(start)
                    await send(body)
                    return {"type": "http.disconnect"}
            return message

        async def guarded_send(message):
            if not answered:  # once we answered 413, whatever the app says is dropped
                await send(message)

        await self.app(scope, limited_receive, guarded_send)


# Label values come from fixed sets only: uvicorn accepts any token as a method, and a label per
# made-up method (or raw path) would grow every scrape without bound.
METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"})


class RequestMetrics:
    """Count requests and time them, by method (``other`` outside :data:`METHODS`), route template
    (``unmatched`` when no route took it) and status."""

    def __init__(self, app, metrics: Metrics):
        self.app, self.metrics = app, metrics

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        t0 = time.perf_counter()
        status = 500

        async def send_status(message):
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_status)
        finally:
            route = scope.get("route")
            path = getattr(route, "path", None) or "unmatched"
            method = scope["method"] if scope["method"] in METHODS else "other"
            self.metrics.observe_request(method, path, status, time.perf_counter() - t0)


class JsonCORS(CORSMiddleware):
    """Starlette's CORS layer, whose refused preflight is the JSON error shape like every other answer."""

    def preflight_response(self, request_headers: Headers) -> Response:
        response = super().preflight_response(request_headers)
        if response.status_code < 400:
            return response
        headers = {k: v for k, v in response.headers.items() if k not in ("content-type", "content-length")}
        refused = bytes(response.body).decode().removeprefix("Disallowed CORS ")
        return error_response(response.status_code, "cors_refused",
                              f"this cross-origin request is not allowed: its {refused}", headers)
