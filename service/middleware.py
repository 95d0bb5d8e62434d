"""ASGI middleware: the upload size cap and request metrics.

Both are plain ASGI (no BaseHTTPMiddleware) so they add microseconds, not a task per request.
"""

from __future__ import annotations

import json
import time

from .metrics import Metrics

# Room for the multipart framing and the small form fields around the file.
MULTIPART_OVERHEAD = 64 * 1024


def _json_error(status: int, code: str, message: str) -> tuple[dict, dict]:
    body = json.dumps({"error": {"code": code, "message": message}}).encode()
    start = {"type": "http.response.start", "status": status,
             "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                         (b"connection", b"close")]}
    return start, {"type": "http.response.body", "body": body}


class BodyLimit:
    """Answer 413 as soon as a request body exceeds ``max_bytes`` (+ multipart overhead).

    A declared Content-Length is checked before reading anything; a chunked body is counted as it
    arrives, and once over the limit the app sees a disconnect while the client gets the 413.
    """

    def __init__(self, app, max_bytes: int):
        self.app, self.limit = app, max_bytes + MULTIPART_OVERHEAD
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
                    start, body = _json_error(413, "too_large", msg)
                    await send(start)
                    await send(body)
                    return
        seen = 0
        answered = False

        async def limited_receive():
            nonlocal seen, answered
            if answered:
                return {"type": "http.disconnect"}
            message = await receive()
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


class RequestMetrics:
    """Count requests and time them, by method, route template and status."""

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
            self.metrics.observe_request(scope["method"], path, status, time.perf_counter() - t0)
