"""Who may change the station's state from the web, and who may follow it live.

- **Token.** Bound to a loopback address (the default, 127.0.0.1) the station needs no token:
  only this computer reaches it. Bound to any other address it refuses to start without one,
  and with a token (:mod:`.tokens`) every state-changing request must carry it: as
  ``Authorization: Bearer TOKEN`` (scripts, factory systems), or as the logged-in session a
  browser gets by giving the token at ``/login`` (:mod:`.sessions`). Without it: HTTP 401.
  Wrong tokens are throttled per client (:mod:`.throttle`): HTTP 429.
- **Cross-site requests.** A state-changing request that is not authenticated by a bearer token
  is a browser's, authenticated by its cookie, and must prove it comes from a page of this
  station: its ``Origin`` (or, without one, its ``Referer``) must be this station's origin
  (``null``, what a browser sends after a cross-origin redirect or from a sandboxed page, is
  refused), a ``Sec-Fetch-Site`` header, when sent, must say ``same-origin``, and it must repeat
  the page's CSRF value (``X-CSRF-Token`` header or ``csrf`` form field), which is bound to the
  browser's session. Otherwise: HTTP 403.
- **Live events.** The event stream refuses other origins, and on a station with a token needs
  the logged-in session (or the bearer token).
- Read-only pages (GET) stay open.

Every refusal raises :class:`AccessError`; the app logs it with the client and the reason.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass
from urllib.parse import urlsplit

from fastapi import Request

from calstation.errors import CalstationError
from calstation.web.hosts import is_local_host, parse_host
from calstation.web.sessions import (
    CSRF_HEADER,
    SESSION_COOKIE,
    SESSION_COOKIE_TLS,
    CsrfKey,
    SessionStore,
    new_session_id,
    valid_session_id,
)
from calstation.web.settings import WebLimits
from calstation.web.throttle import LoginThrottle, retry_after
from calstation.web.tokens import TokenSource, TokenUnavailable

__all__ = ["AccessError", "Guard", "is_local_host"]

log = logging.getLogger("calstation.web")


class AccessError(CalstationError):
    """A request without the right to do what it asks; ``status`` is 401, 403, 429 or 503."""

    def __init__(self, status: int, message: str, headers: Mapping[str, str] | None = None
                 ) -> None:
        super().__init__(message)
        self.status = status
        self.headers = dict(headers or {})


def client_of(request: Request) -> str:
    """The client's address (the key of per-client limits)."""
    return request.client.host if request.client else "unknown"


def _origin_tuple(scheme: str, netloc: str) -> tuple[str, object, int] | None:
    parsed = parse_host(netloc)
    if parsed is None or scheme not in ("http", "https"):
        return None
    host, port = parsed
    return scheme, host, port if port is not None else (443 if scheme == "https" else 80)


@dataclass(frozen=True)
class PageSession:
    """The session a page is rendered for: its id, its CSRF value, and whether the response
    must set the cookie (a browser without one)."""

    session_id: str
    csrf: str
    new: bool


class Guard:
    """Checks requests against the token, the session and their origin (see the module
    docstring). One per app."""

    def __init__(self, token: TokenSource | None, *, require_token: bool, tls: bool = False,
                 limits: WebLimits | None = None) -> None:
        if require_token and token is None:
            raise CalstationError(
                "serving on a non-local address needs a station token: set $CALSTATION_TOKEN or "
                "pass --token-file FILE (or serve on 127.0.0.1)"
            )
        limits = limits or WebLimits()
        self.token = token
        self.require_token = require_token
        self.tls = tls
        self.limits = limits
        self.cookie_name = SESSION_COOKIE_TLS if tls else SESSION_COOKIE
        self.csrf = CsrfKey()
        self.sessions = SessionStore(idle_s=limits.session_idle_s,
                                     max_age_s=limits.session_max_s,
                                     capacity=limits.max_sessions, clock=limits.clock)
        self.throttle = LoginThrottle(free=limits.login_free_failures,
                                      max_lock_s=limits.login_max_lock_s,
                                      window_s=limits.login_window_s, clock=limits.clock)
        self._generation = token.generation if token is not None else 0
        self._unavailable: str | None = None

    # --- the token -------------------------------------------------------------------------
    def _token_generation(self) -> int:
        """The token generation now in force (ending the sessions of an older one); sets
        ``_unavailable`` while the token file cannot be used."""
        if self.token is None:
            return 0
        try:
            self.token.current()
            if self._unavailable is not None:
                log.warning("the station token can be read again")
            self._unavailable = None
        except TokenUnavailable as exc:
            if self._unavailable is None:
                log.error("the station token is unavailable, every change is refused: %s", exc)
            self._unavailable = str(exc)
        generation = self.token.generation
        if generation != self._generation:
            self._generation = generation
            ended = self.sessions.end_generation(generation)
            log.warning("the station token changed: %d logged-in session(s) ended", ended)
        return generation

    def _bearer(self, request: Request) -> bool:
        """True when the request carries the right bearer token, False when it carries no
        ``Authorization`` header; AccessError for a wrong one (counted by the throttle)."""
        auth = request.headers.get("authorization")
        if auth is None:
            return False
        scheme, _, value = auth.partition(" ")
        if scheme.lower() != "bearer" or not value.strip():
            raise AccessError(401, "Authorization must be 'Bearer TOKEN'")
        self._check_token(request, value.strip())
        return True

    def _check_token(self, request: Request, candidate: str) -> None:
        client = client_of(request)
        wait = self.throttle.wait_s(client)
        if wait > 0:
            raise AccessError(429, f"too many wrong tokens from {client}: wait {wait:.0f} s",
                              {"Retry-After": retry_after(wait)})
        if self.token is None:
            raise AccessError(401, "this station has no token: it takes none")
        self._token_generation()
        if self._unavailable is not None:
            raise AccessError(503, f"the station token is unavailable: {self._unavailable}")
        if self.token.matches(candidate):
            self.throttle.succeeded(client)
            return
        lock = self.throttle.failed(client)
        raise AccessError(401, "wrong station token" + (
            f"; {client} must now wait {lock:.0f} s before the next try" if lock else ""),
            {"Retry-After": retry_after(lock)} if lock else None)

    # --- sessions --------------------------------------------------------------------------
    def session_id(self, request: Request) -> str | None:
        """The request's session id (None without a well-formed session cookie)."""
        return valid_session_id(request.cookies.get(self.cookie_name))

    def logged_in(self, request: Request) -> bool:
        """Does the request come from a logged-in session (always True without a token)."""
        if not self.require_token:
            return True
        return self.sessions.check(self.session_id(request), self._token_generation()) is None

    def page_session(self, request: Request) -> PageSession:
        """The session a page is rendered for (a new one for a browser without a cookie)."""
        sid = self.session_id(request)
        if sid is not None:
            return PageSession(sid, self.csrf.value(sid), False)
        sid = new_session_id()
        return PageSession(sid, self.csrf.value(sid), True)

    def cookie_args(self, *, logged_in: bool) -> dict[str, object]:
        """The attributes of the session cookie."""
        args: dict[str, object] = {"httponly": True, "samesite": "strict", "secure": self.tls,
                                   "path": "/"}
        if logged_in:
            args["max_age"] = int(self.limits.session_max_s)
        return args

    def login(self, request: Request, candidate: str) -> str | None:
        """Check ``candidate`` against the token (throttled); the new logged-in session's id,
        or None on a station without a token. AccessError when wrong."""
        if not self.require_token:
            return None
        self._check_token(request, candidate)
        self.sessions.close(self.session_id(request))
        sid = self.sessions.open(self._token_generation())
        log.info("logged in from %s", client_of(request))
        return sid

    def logout(self, request: Request) -> None:
        """End the request's logged-in session (if any)."""
        if self.sessions.close(self.session_id(request)):
            log.info("logged out from %s", client_of(request))

    # --- checks ----------------------------------------------------------------------------
    def own_origin(self, request: Request) -> tuple[str, object, int] | None:
        """This station's origin as the request addressed it (scheme, host, port)."""
        return _origin_tuple(request.url.scheme, request.headers.get("host", ""))

    def _check_origin(self, request: Request, *, required: bool) -> None:
        origin = request.headers.get("origin")
        if origin is None and required:
            origin = request.headers.get("referer")
            if origin is None:
                raise AccessError(403, "cross-site check failed: the request has neither Origin "
                                       "nor Referer (a script should send Authorization: Bearer)")
        if origin == "null":
            raise AccessError(403, "cross-site request refused (Origin: null, as after a "
                                   "cross-origin redirect)")
        if origin is not None:
            try:
                parts = urlsplit(origin)
                theirs = _origin_tuple(parts.scheme.lower(), parts.netloc)
            except ValueError:
                theirs = None
            if theirs is None or theirs != self.own_origin(request):
                raise AccessError(403, f"cross-site request from {origin[:100]!r} refused")
        # what the browser itself says of where the request comes from (no script can set it)
        site = request.headers.get("sec-fetch-site")
        if site is not None and site != "same-origin" and (required or site != "none"):
            raise AccessError(403, f"cross-site request refused (Sec-Fetch-Site: {site[:40]})")

    def check_write(self, request: Request, form_csrf: str | None, *, login: bool = False
                    ) -> None:
        """Raise :class:`AccessError` unless the request may change the station's state
        (``login``: the login and logout forms, which need no logged-in session)."""
        if self._bearer(request):
            return
        self._check_origin(request, required=True)
        sid = self.session_id(request)
        if sid is None:
            raise AccessError(403, "no session cookie: reload the page and try again")
        given = request.headers.get(CSRF_HEADER) or form_csrf or ""
        if not self.csrf.check(sid, given):
            raise AccessError(403, "missing or wrong CSRF value: reload the page and try again")
        if self.require_token and not login:
            self._check_logged_in(sid)

    def _check_logged_in(self, sid: str | None) -> None:
        generation = self._token_generation()
        if self._unavailable is not None:
            raise AccessError(503, f"the station token is unavailable: {self._unavailable}")
        why = self.sessions.check(sid, generation)
        if why is not None:
            detail = {"expired": "your session expired",
                      "token changed": "the station token changed"}.get(why, "not logged in")
            raise AccessError(401, f"this station needs its token ({detail}): log in at "
                                   "/login (or send Authorization: Bearer TOKEN)")

    def check_stream(self, request: Request) -> None:
        """Raise :class:`AccessError` unless the request may open an event stream."""
        self._check_origin(request, required=False)
        if self._bearer(request) or not self.require_token:
            return
        self._check_logged_in(self.session_id(request))
