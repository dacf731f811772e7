"""How the dashboard is served: listen address, TLS, a cap on connections, JSON errors and
security headers (the HTTP plumbing under :mod:`fbgcomp.dashboard.server`, which holds what is
served).

Every answer carries :data:`SECURITY_HEADERS`; a refused request (:class:`Refused`, or one of
aiohttp's own 4xx) is answered ``{"error": message}``. At most ``max_connections`` connections
are open at a time (the one thing aiohttp has no setting for: :class:`ConnectionCap`); one more
is answered 503 and closed at once.
"""

from __future__ import annotations

import asyncio
import ipaddress
import json
import ssl
from collections.abc import Callable
from pathlib import Path

from aiohttp import web

from fbgcomp.errors import InputError

DEFAULT_HOST = "127.0.0.1"
SECURITY_HEADERS = {
    "Cache-Control": "no-store",
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "no-referrer",
    "Content-Security-Policy": "default-src 'self'; img-src 'self' data:; object-src 'none'; "
    "frame-ancestors 'none'; base-uri 'none'; form-action 'self'",
    "Server": "fbgcomp-dashboard",
}


def parse_listen(listen: str) -> tuple[str, int]:
    """``[HOST:]PORT`` (``[::1]:8080`` for IPv6) -> (host, port), host 127.0.0.1 if omitted."""
    text = listen.strip()
    host, sep, port = text.rpartition(":")
    if not sep:
        host, port = "", text
    host = host.strip("[]") or DEFAULT_HOST
    if not port.isdigit() or not 0 <= int(port) <= 65535:
        raise InputError(
            f"expected [HOST:]PORT, e.g. 8080 or 127.0.0.1:8080, got {listen!r}", column="--dashboard"
        )
    return host, int(port)


def is_loopback(host: str) -> bool:
    """True for ``localhost`` and loopback addresses; a host name may resolve beyond: False."""
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def tls_context(cert: str | None, key: str | None) -> ssl.SSLContext | None:
    """Server TLS context from PEM files (TLS 1.2 at least), None without either."""
    if not cert and not key:
        return None
    if not (cert and key):
        raise InputError(
            "TLS needs both a certificate and its private key", column="--dashboard-cert/--dashboard-key"
        )
    ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    for path in (cert, key):
        if not Path(path).is_file():
            raise InputError("TLS certificate or key file not found", file=path)
    try:
        ctx.load_cert_chain(cert, key)
    except (ssl.SSLError, ValueError) as exc:
        # the reason only (e.g. KEY_VALUES_MISMATCH), never the file's content
        reason = getattr(exc, "reason", None) or type(exc).__name__
        raise InputError(f"cannot use this TLS certificate and key ({reason})", file=cert) from None
    return ctx


def json_response(data, status: int = 200, headers=None) -> web.Response:
    """``data`` as an ``application/json`` answer."""
    return web.Response(
        body=json.dumps(data).encode(), status=status, content_type="application/json", headers=headers
    )


class Refused(Exception):
    """A request answered with ``{"error": message}``; ``close``: the connection too."""

    def __init__(self, status: int, message: str, close: bool = False):
        super().__init__(message)
        self.status, self.message, self.close = status, message, close


@web.middleware
async def errors_as_json(request: web.Request, handler):
    """Middleware: a :class:`Refused` request, or one of aiohttp's own errors (404, 405,
    413...), answered ``{"error": message}``."""
    try:
        return await handler(request)
    except Refused as exc:
        resp = json_response({"error": exc.message}, exc.status)
        if exc.close:
            resp.force_close()
        return resp
    except web.HTTPException as exc:  # aiohttp's own 404, 405, 413...
        if exc.status < 400:
            raise
        allow = {"Allow": exc.headers["Allow"]} if "Allow" in exc.headers else None
        return json_response({"error": (exc.reason or "error").lower()}, exc.status, headers=allow)


async def security_headers(request: web.Request, response: web.StreamResponse) -> None:
    """``on_response_prepare`` hook: every answer carries :data:`SECURITY_HEADERS`."""
    for name, value in SECURITY_HEADERS.items():
        response.headers[name] = value


_BUSY_BODY = b'{"error": "too many connections"}'
_BUSY = (
    b"HTTP/1.1 503 Service Unavailable\r\nContent-Type: application/json\r\n"
    b"Content-Length: %d\r\nRetry-After: 5\r\nConnection: close\r\n\r\n%s" % (len(_BUSY_BODY), _BUSY_BODY)
)


class ConnectionCap:
    """Protocol factory for ``loop.create_server``: aiohttp's server (its documented protocol
    factory), with at most ``limit`` connections open; one more is answered 503 and closed.

    Counted when a connection is made, not when the factory is called: a burst of accepts calls
    the factory many times before any connection is made."""

    def __init__(self, factory: Callable[[], asyncio.Protocol], limit: int):
        self.factory, self.limit, self.open, self.refused = factory, max(1, int(limit)), 0, 0

    def __call__(self) -> asyncio.Protocol:
        """A protocol for one new connection."""
        return CappedProtocol(self)


class CappedProtocol(asyncio.Protocol):
    """Hands every transport event (the ``asyncio.Protocol`` methods) to an aiohttp request
    handler, if the cap lets the connection in."""

    __slots__ = ("cap", "inner")

    def __init__(self, cap: ConnectionCap):
        self.cap = cap
        self.inner: asyncio.Protocol | None = None

    def connection_made(self, transport) -> None:
        """Let the connection in, or answer 503 and close it when ``limit`` are open."""
        cap = self.cap
        if cap.open >= cap.limit:
            cap.refused += 1
            transport.write(_BUSY)
            transport.close()
            return
        cap.open += 1
        inner = self.inner = cap.factory()
        inner.connection_made(transport)

    def connection_lost(self, exc) -> None:
        """Count the connection out of the cap and pass the loss on to the handler."""
        inner, self.inner = self.inner, None
        if inner is not None:
            self.cap.open -= 1
            inner.connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        """Pass the received bytes on to the handler (dropped for a refused connection)."""
        if self.inner is not None:
            self.inner.data_received(data)

    def eof_received(self):
        """The handler's answer to end of stream; None (close) for a refused connection."""
        return self.inner.eof_received() if self.inner is not None else None

    def pause_writing(self) -> None:
        """Pass the transport's flow-control pause on to the handler."""
        if self.inner is not None:
            self.inner.pause_writing()

    def resume_writing(self) -> None:
        """Pass the transport's flow-control resume on to the handler."""
        if self.inner is not None:
            self.inner.resume_writing()
