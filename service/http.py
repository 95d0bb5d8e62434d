"""uvicorn's HTTP/1.1 protocol (h11) with the service's answers where uvicorn answers by itself.

uvicorn answers a malformed request with a plain-text 400 and waits for a request's headers for as long as the
client takes.  ``Protocol`` answers both in the service's JSON error shape, and closes a connection whose request
line and headers are not complete ``header_timeout_seconds`` after their first byte (or after the connection
opened) with 408: a client dripping headers byte by byte holds a connection for that long, not for ever.
(Bodies have their own timeouts, ``middleware.BodyLimit``.)  uvicorn also believes ``X-Forwarded-For`` from
loopback by default, so any local client could name its own address and escape the per-address limits;
``Protocol`` believes it only from the app's ``trusted_proxies`` (none by default).  Serve with
``uvicorn service.app:create_app --factory --http service.http:Protocol``.
"""

from __future__ import annotations

import asyncio
import functools

import h11
from uvicorn.middleware.proxy_headers import ProxyHeadersMiddleware
from uvicorn.protocols.http.h11_impl import H11Protocol

from .errors import error_body


@functools.cache
def header_timeout() -> float:
    from fastmesh_jobs.settings import Settings

    return Settings().header_timeout_seconds


def error_bytes(status: int, reason: str, code: str, message: str) -> bytes:
    """A whole HTTP/1.1 error response in the service's JSON shape, closing the connection."""
    body = error_body(code, message)
    head = (f"HTTP/1.1 {status} {reason}\r\ncontent-type: application/json\r\ncontent-length: {len(body)}\r\n"
            "connection: close\r\n\r\n")
    return head.encode() + body


def trusting_only(app, config) -> object:
    """``app`` (uvicorn's loaded app) with ``X-Forwarded-For`` believed only from the FastAPI app's
    ``settings.trusted_proxies``: uvicorn's proxy-header layer is replaced by one trusting those alone, or
    removed when there are none.  Made once per server config."""
    cached = getattr(config, "_fastmesh_app", None)
    if cached is not None:
        return cached
    inner = app.app if isinstance(app, ProxyHeadersMiddleware) else None
    settings = getattr(getattr(inner, "state", None), "settings", None)
    if settings is not None:
        proxies = list(settings.trusted_proxies)
        app = ProxyHeadersMiddleware(inner, trusted_hosts=proxies) if proxies else inner
    config._fastmesh_app = app
    return app


class Protocol(H11Protocol):
    _header_timer: asyncio.TimerHandle | None = None

    def __init__(self, config, *args, **kwargs) -> None:
        super().__init__(config, *args, **kwargs)
        self.app = trusting_only(self.app, config)

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm_header_timer()

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        if self.conn.their_state is h11.IDLE and data:
            self._arm_header_timer()  # a request has begun: its headers must be complete in time
        else:
            self._cancel_header_timer()

    def connection_lost(self, exc: Exception | None) -> None:
        self._cancel_header_timer()
        super().connection_lost(exc)

    def send_400_response(self, msg: str) -> None:
        self._cancel_header_timer()
        self._close_with(error_bytes(400, "Bad Request", "bad_request", f"malformed HTTP request: {msg}"))

    def _arm_header_timer(self) -> None:
        if self._header_timer is None:
            self._header_timer = self.loop.call_later(header_timeout(), self._headers_too_slow)

    def _cancel_header_timer(self) -> None:
        if self._header_timer is not None:
            self._header_timer.cancel()
            self._header_timer = None

    def _headers_too_slow(self) -> None:
        self._header_timer = None
        if self.conn.their_state is h11.IDLE:
            self._close_with(error_bytes(408, "Request Timeout", "timeout",
                                         f"the request line and headers did not arrive within {header_timeout():g} s"))

    def _close_with(self, response: bytes) -> None:
        if not self.transport.is_closing():
            self.transport.write(response)
            self.transport.close()
