"""Who may change the station's state from the web: the station token and CSRF protection.

- Bound to a loopback address (the default, 127.0.0.1) the station needs no token: only this
  computer reaches it. Bound to any other address it refuses to start without a token (from
  ``$CALSTATION_TOKEN``, or the file named by ``--token-file`` / ``$CALSTATION_TOKEN_FILE``), and
  every state-changing request (start, answer, retry, abort, resume) must carry it: either as
  ``Authorization: Bearer TOKEN`` (scripts, factory systems) or as the session cookie a browser
  gets from the login page. Without it: HTTP 401, and nothing moves.
- Every state-changing request coming from a browser (with cookies) is also CSRF-checked: it must
  repeat the page's CSRF value (a random per-browser cookie) in the ``X-CSRF-Token`` header or
  the ``csrf`` form field, and its ``Origin``, when sent, must be this server. Another site can
  neither read the value nor set the header, so it cannot make the operator's browser start or
  abort a run. Failures: HTTP 403.
- Read-only pages (GET) stay open.
"""

from __future__ import annotations

import hashlib
import hmac
import ipaddress
import os
import secrets
from pathlib import Path
from urllib.parse import urlsplit

from calstation.errors import CalstationError

CSRF_COOKIE = "calstation_csrf"
SESSION_COOKIE = "calstation_session"
CSRF_HEADER = "x-csrf-token"


class AccessError(CalstationError):
    """A state-changing request without the right to make it; ``status`` is 401 or 403."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status


def is_local_host(host: str) -> bool:
    """True for a loopback bind address (127.0.0.0/8, ::1, localhost)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def load_token(token_file: Path | None = None) -> str | None:
    """The station token: ``$CALSTATION_TOKEN``, else the first line of ``token_file`` (or of
    ``$CALSTATION_TOKEN_FILE``); None when neither is set. An empty or short token is refused."""
    token = os.environ.get("CALSTATION_TOKEN")
    source = "$CALSTATION_TOKEN"
    if not token:
        path = token_file or (Path(os.environ["CALSTATION_TOKEN_FILE"])
                              if os.environ.get("CALSTATION_TOKEN_FILE") else None)
        if path is None:
            return None
        try:
            token = path.read_text(encoding="utf-8").strip().splitlines()[0].strip()
        except (OSError, IndexError) as exc:
            raise CalstationError(f"cannot read the station token from {path}: {exc}") from exc
        source = str(path)
    if len(token) < 12:
        raise CalstationError(f"the station token from {source} is too short: use at least 12 "
                              "characters (e.g. from `openssl rand -hex 16`)")
    return token


class Guard:
    """Checks state-changing requests (see the module docstring)."""

    def __init__(self, token: str | None, require_token: bool) -> None:
        if require_token and not token:
            raise CalstationError(
                "serving on a non-local address needs a station token: set $CALSTATION_TOKEN or "
                "pass --token-file FILE (or serve on 127.0.0.1)"
            )
        self.token = token
        self.require_token = require_token

    def session_value(self) -> str:
        """The browser session cookie's value after a login (derived from the token)."""
        assert self.token is not None
        return hmac.new(self.token.encode(), b"calstation-session", hashlib.sha256).hexdigest()

    def check_token(self, candidate: str) -> bool:
        """Is ``candidate`` the station token (constant-time)."""
        return self.token is not None and hmac.compare_digest(candidate.encode(),
                                                              self.token.encode())

    def check(
        self,
        *,
        method: str,
        headers: dict[str, str],
        cookies: dict[str, str],
        form_csrf: str | None,
        host_url: str,
        login: bool = False,
    ) -> None:
        """Raise :class:`AccessError` unless the request may change the station's state
        (``login``: the login form itself, which needs only the CSRF check)."""
        if method in ("GET", "HEAD", "OPTIONS"):
            return
        auth = headers.get("authorization", "")
        if auth.lower().startswith("bearer "):
            # a script with the token: no ambient browser credentials, so no CSRF to fear
            if self.check_token(auth[7:].strip()):
                return
            raise AccessError(401, "wrong station token")
        if self.require_token and not login:
            session = cookies.get(SESSION_COOKIE, "")
            if not session or not hmac.compare_digest(session, self.session_value()):
                raise AccessError(401, "this station needs its token: log in at /login (or send "
                                       "Authorization: Bearer TOKEN)")
        self._check_csrf(headers, cookies, form_csrf, host_url)

    @staticmethod
    def _check_csrf(headers: dict[str, str], cookies: dict[str, str], form_csrf: str | None,
                    host_url: str) -> None:
        origin = headers.get("origin")
        if origin and origin != "null":
            want = urlsplit(host_url)
            got = urlsplit(origin)
            if (got.scheme, got.netloc) != (want.scheme, want.netloc):
                raise AccessError(403, f"cross-site request from {origin} refused")
        expected = cookies.get(CSRF_COOKIE, "")
        given = headers.get(CSRF_HEADER) or form_csrf or ""
        if not expected or not given or not hmac.compare_digest(expected, given):
            raise AccessError(403, "missing or wrong CSRF value: reload the page and try again")


def new_csrf_value() -> str:
    """A fresh random CSRF value for a browser."""
    return secrets.token_urlsafe(24)
