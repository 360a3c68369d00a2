"""Browser sessions and the CSRF value bound to each.

Every browser gets a session cookie: 32 random bytes, ``HttpOnly`` (no script reads it),
``SameSite=Strict``, ``Secure`` and ``__Host-``-prefixed when served over TLS. The page's CSRF
value is an HMAC of the session id under a key that never leaves the server process, so it is
bound to the session: a value read from one browser's page is worthless with another session,
and another port on the same host (which shares the cookie jar) can neither read the session
id nor derive the value.

A session becomes *logged in* when its browser gives the station token at ``/login``: the
server then issues a new session id (the old one, which a page on another port could have
planted, is not promoted) and keeps it in a :class:`SessionStore`, with the token generation it
was opened under. A logged-in session ends when it has been idle too long, when it is too old,
at logout, or when the token changes. Sessions that never logged in are not stored: there is
nothing to remember about them, and nothing for a flood of cookie-less requests to fill.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import re
import secrets
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

from calstation.web.tokens import as_bytes

SESSION_COOKIE = "calstation_session"
SESSION_COOKIE_TLS = "__Host-calstation_session"
CSRF_HEADER = "x-csrf-token"
CSRF_FIELD = "csrf"

_SESSION_ID = re.compile(r"[A-Za-z0-9_-]{43}")


def new_session_id() -> str:
    """A fresh random session id (256 bits, URL-safe)."""
    return secrets.token_urlsafe(32)


def valid_session_id(value: str | None) -> str | None:
    """``value`` if it has the shape of a session id the server issues, else None (a forged
    cookie of another length or alphabet, or non-ASCII, is ignored, never an error)."""
    return value if value is not None and _SESSION_ID.fullmatch(value) else None


@dataclass
class Session:
    """A logged-in session."""

    created: float
    last_seen: float
    generation: int


class CsrfKey:
    """Derives the CSRF value of a session (HMAC-SHA256 under a per-process random key)."""

    def __init__(self, key: bytes | None = None) -> None:
        self._key = key or secrets.token_bytes(32)

    def value(self, session_id: str) -> str:
        """The CSRF value of ``session_id`` (URL-safe text, for a page and its forms)."""
        mac = hmac.new(self._key, b"calstation-csrf\0" + session_id.encode("ascii"),
                       hashlib.sha256).digest()
        return base64.urlsafe_b64encode(mac).decode("ascii").rstrip("=")

    def check(self, session_id: str, given: str) -> bool:
        """Is ``given`` the CSRF value of ``session_id`` (constant time, on bytes)."""
        return hmac.compare_digest(as_bytes(given), self.value(session_id).encode("ascii"))


class SessionStore:
    """The logged-in sessions (thread-safe; keyed by a hash of the id, so that the ids
    themselves are nowhere in the server's memory but in the request being served)."""

    def __init__(self, *, idle_s: float, max_age_s: float, capacity: int,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.idle_s, self.max_age_s, self.capacity = idle_s, max_age_s, capacity
        self.clock = clock
        self._lock = threading.Lock()
        self._sessions: OrderedDict[bytes, Session] = OrderedDict()

    @staticmethod
    def _key(session_id: str) -> bytes:
        return hashlib.sha256(session_id.encode("ascii")).digest()

    def open(self, generation: int) -> str:
        """A new logged-in session under token ``generation``; returns its id. The oldest
        session is dropped when the store is full."""
        sid = new_session_id()
        now = self.clock()
        with self._lock:
            self._sessions[self._key(sid)] = Session(now, now, generation)
            while len(self._sessions) > self.capacity:
                self._sessions.popitem(last=False)
        return sid

    def check(self, session_id: str | None, generation: int) -> str | None:
        """None if ``session_id`` is logged in (and touch it), else why not: ``"none"`` (no
        such session), ``"expired"`` or ``"token changed"``. An ended session is forgotten."""
        if session_id is None:
            return "none"
        key = self._key(session_id)
        now = self.clock()
        with self._lock:
            session = self._sessions.get(key)
            if session is None:
                return "none"
            if session.generation != generation:
                del self._sessions[key]
                return "token changed"
            if now - session.last_seen > self.idle_s or now - session.created > self.max_age_s:
                del self._sessions[key]
                return "expired"
            session.last_seen = now
            self._sessions.move_to_end(key)
            return None

    def close(self, session_id: str | None) -> bool:
        """Log ``session_id`` out; True if it was logged in."""
        if session_id is None:
            return False
        with self._lock:
            return self._sessions.pop(self._key(session_id), None) is not None

    def end_generation(self, generation: int) -> int:
        """How many sessions were not opened under ``generation`` (the token changed): each
        is refused from now on, saying why, and then forgotten."""
        with self._lock:
            return sum(s.generation != generation for s in self._sessions.values())

    def __len__(self) -> int:
        with self._lock:
            return len(self._sessions)
