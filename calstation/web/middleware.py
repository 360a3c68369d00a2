"""The outermost layer of the web station, around everything FastAPI does (even its error
pages): the ``Host`` allow-list, the request body limit, and the security headers of every
response.

Headers on every response:

- ``Content-Security-Policy``: scripts and styles only from the station itself or carrying the
  response's nonce (no inline handlers, no ``eval``), nothing from anywhere else, no framing
  (``frame-ancestors 'none'``), forms post only to the station; a route may set a stricter
  policy of its own (the offline report file does);
- ``X-Frame-Options: DENY`` (for browsers without ``frame-ancestors``),
  ``X-Content-Type-Options: nosniff``, ``Referrer-Policy: no-referrer``,
  ``Cross-Origin-Opener-Policy`` and ``Cross-Origin-Resource-Policy: same-origin``, and
  ``Cache-Control: no-store`` unless the route says otherwise; ``Strict-Transport-Security``
  over TLS;
- no ``Server`` banner (``calstation serve`` also turns off uvicorn's).

A body is refused (413) from its ``Content-Length`` before a byte of it is read, and a body
sent without a length is counted as it arrives and refused once past the limit, so a huge body
costs the server neither memory nor parsing.
"""

from __future__ import annotations

import logging
import secrets

from starlette.datastructures import Headers
from starlette.exceptions import HTTPException
from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from calstation.web.hosts import HostPolicy

log = logging.getLogger("calstation.web")

NONCE_KEY = "calstation.csp_nonce"
"""Where the response's CSP nonce is kept in the ASGI scope (templates put it on scripts)."""


def page_policy(nonce: str) -> str:
    """The Content-Security-Policy of the station's pages."""
    return ("default-src 'none'; "
            f"script-src 'self' 'nonce-{nonce}' 'report-sample'; "
            f"style-src 'self' 'nonce-{nonce}' 'report-sample'; "
            "img-src 'self' data: blob:; font-src 'self'; connect-src 'self'; "
            "form-action 'self'; base-uri 'none'; frame-ancestors 'none'; object-src 'none'")


HEADERS = {
    "x-frame-options": "DENY",
    "x-content-type-options": "nosniff",
    "referrer-policy": "no-referrer",
    "cross-origin-opener-policy": "same-origin",
    "cross-origin-resource-policy": "same-origin",
    "permissions-policy": "camera=(), microphone=(), geolocation=(), usb=(), serial=()",
    "cache-control": "no-store",
}


class BodyTooLarge(HTTPException):
    """A request body past the limit (HTTP 413)."""

    def __init__(self, limit: int) -> None:
        super().__init__(413, f"request body larger than {limit} bytes")


def describe(scope: Scope) -> str:
    """``METHOD /path from CLIENT`` for a log line (the path cut short, control characters
    escaped)."""
    client = scope.get("client")
    path = repr(scope.get("path", ""))[1:-1][:200]
    return f"{scope.get('method', '?')} {path} from {client[0] if client else 'unknown'}"


def refused(scope: Scope, status: int, reason: str) -> None:
    """Log a refused request with its reason."""
    log.warning("refused %s: %d %s", describe(scope), status, repr(reason)[1:-1][:300])


class FrontDoor:
    """ASGI middleware: see the module docstring."""

    def __init__(self, app: ASGIApp, *, hosts: HostPolicy, max_body_bytes: int,
                 tls: bool = False) -> None:
        self.app = app
        self.hosts = hosts
        self.max_body_bytes = max_body_bytes
        self.tls = tls

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            if scope["type"] == "websocket":  # the station has none: close without a word
                await send({"type": "websocket.close", "code": 1008})
                return
            await self.app(scope, receive, send)
            return
        nonce = secrets.token_urlsafe(18)
        scope[NONCE_KEY] = nonce
        send = self._with_headers(send, nonce)
        headers = Headers(scope=scope)
        server = scope.get("server")
        refusal = self.hosts.refusal(headers.get("host"), server[0] if server else None)
        if refusal is None:
            refusal = self._body_refusal(headers)
        if refusal is not None:
            status, reason = refusal
            refused(scope, status, reason)
            await JSONResponse({"error": reason}, status_code=status)(scope, receive, send)
            return
        await self.app(scope, self._limited(receive), send)

    def _body_refusal(self, headers: Headers) -> tuple[int, str] | None:
        length = headers.get("content-length")
        if length is None:
            return None
        if not (length.isascii() and length.isdigit()) or len(length) > 18:
            return 400, f"malformed Content-Length {length[:40]!r}"
        if int(length) > self.max_body_bytes:
            return 413, f"request body of {int(length)} bytes, more than {self.max_body_bytes}"
        return None

    def _limited(self, receive: Receive) -> Receive:
        seen = 0
        limit = self.max_body_bytes

        async def limited() -> Message:
            nonlocal seen
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > limit:
                    raise BodyTooLarge(limit)
            return message

        return limited

    def _with_headers(self, send: Send, nonce: str) -> Send:
        extra = dict(HEADERS)
        extra["content-security-policy"] = page_policy(nonce)
        if self.tls:
            extra["strict-transport-security"] = "max-age=31536000"

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                raw = [(k, v) for k, v in message.get("headers", []) if k.lower() != b"server"]
                present = {k.lower() for k, _ in raw}
                raw += [(k.encode(), v.encode()) for k, v in extra.items()
                        if k.encode() not in present]
                message["headers"] = raw
            await send(message)

        return send_with_headers
