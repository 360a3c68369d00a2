"""The station token: where it comes from, when it changes, and how a candidate is compared.

The token is ``$CALSTATION_TOKEN``, else the first line of a token file (``--token-file`` or
``$CALSTATION_TOKEN_FILE``). A token file is read again whenever the token is needed: when it
is rewritten (a new token), the next request sees the new token, and every session opened with
the old one ends (:mod:`.sessions` keeps each session's token generation). A token file that
can no longer be read locks the station (every state-changing request is refused) until it
can.

Comparisons are on bytes, of SHA-256 digests, with :func:`hmac.compare_digest`: constant time,
independent of the candidate's length, and a candidate that is not ASCII is simply wrong.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import threading
from pathlib import Path

from calstation.errors import CalstationError

TOKEN_MIN_LENGTH = 12
TOKEN_MAX_LENGTH = 256


class TokenUnavailable(CalstationError):
    """The token file was changed into something that is not a usable token, or vanished."""


def as_bytes(text: str) -> bytes:
    """``text`` as bytes for a comparison: UTF-8, with whatever the server decoded from a
    header (Latin-1) or a cookie (possibly lone surrogates) kept, never an exception."""
    return text.encode("utf-8", "surrogatepass")


def same_secret(candidate: str, secret: str) -> bool:
    """Is ``candidate`` equal to ``secret``, in constant time (any text, any length)."""
    return hmac.compare_digest(hashlib.sha256(as_bytes(candidate)).digest(),
                               hashlib.sha256(as_bytes(secret)).digest())


def check_token_text(token: str, source: str) -> str:
    """``token`` if it is usable as a station token (12–256 printable ASCII characters, no
    spaces), else a :class:`CalstationError` that names ``source``."""
    if len(token) < TOKEN_MIN_LENGTH:
        raise CalstationError(f"the station token from {source} is too short: use at least "
                              f"{TOKEN_MIN_LENGTH} characters (e.g. from `openssl rand -hex 16`)")
    if len(token) > TOKEN_MAX_LENGTH:
        raise CalstationError(f"the station token from {source} is longer than "
                              f"{TOKEN_MAX_LENGTH} characters")
    if not all("!" <= c <= "~" for c in token):
        raise CalstationError(f"the station token from {source} must be printable ASCII without "
                              "spaces (e.g. from `openssl rand -hex 16`)")
    return token


def _read_token_file(path: Path) -> str:
    try:
        with path.open("rb") as f:  # the first line is all that counts: read no more
            head = f.read(4 * TOKEN_MAX_LENGTH)
        lines = head.decode("utf-8", "replace").strip().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise TokenUnavailable(f"cannot read the station token from {path}: {exc}") from exc
    if not lines:
        raise TokenUnavailable(f"the token file {path} is empty")
    try:
        return check_token_text(lines[0].strip(), str(path))
    except CalstationError as exc:
        raise TokenUnavailable(str(exc)) from exc


class TokenSource:
    """The station token, fixed or read from a file that is re-read when it changes.

    ``generation`` grows with every change of the token, so that sessions opened with an older
    token can be told apart. :meth:`current` raises :class:`TokenUnavailable` while the file
    cannot be read.
    """

    def __init__(self, token: str | None = None, path: Path | None = None,
                 source: str = "the station token") -> None:
        if (token is None) == (path is None):
            raise ValueError("give a token or a token file")
        self.path = path
        self.source = str(path) if path is not None else source
        self.generation = 0
        self._lock = threading.Lock()
        self._token: str | None = None
        self._error: TokenUnavailable | None = None
        if token is not None:
            self._token = check_token_text(token.strip(), source)
        else:
            assert path is not None
            try:
                self._token = _read_token_file(path)
            except TokenUnavailable as exc:
                raise CalstationError(str(exc)) from exc

    @classmethod
    def from_environment(cls, token_file: Path | None = None) -> TokenSource | None:
        """``$CALSTATION_TOKEN``, else ``token_file``, else ``$CALSTATION_TOKEN_FILE``; None
        when none is set. A short or unreadable token is a :class:`CalstationError`."""
        token = os.environ.get("CALSTATION_TOKEN")
        if token:
            return cls(token=token, source="$CALSTATION_TOKEN")
        path = token_file or (Path(os.environ["CALSTATION_TOKEN_FILE"])
                              if os.environ.get("CALSTATION_TOKEN_FILE") else None)
        return None if path is None else cls(path=path)

    def current(self) -> str:
        """The token now in force (its file read again)."""
        if self.path is None:
            assert self._token is not None
            return self._token
        with self._lock:
            # read every time (a few hundred bytes): a rewrite within the file system's time
            # resolution, to the same size, is still seen
            try:
                token = _read_token_file(self.path)
            except TokenUnavailable as exc:
                # fail closed: no token is accepted until the file is usable again
                if self._error is None:
                    self.generation += 1
                self._token, self._error = None, exc
                raise
            if token != self._token:
                self._token = token
                self.generation += 1
            self._error = None
            return token

    def matches(self, candidate: str) -> bool:
        """Is ``candidate`` the current token (constant time)."""
        try:
            token = self.current()
        except TokenUnavailable:
            return False
        return same_secret(candidate, token)


def load_token(token_file: Path | None = None) -> str | None:
    """The station token now (see :meth:`TokenSource.from_environment`); None when unset."""
    source = TokenSource.from_environment(token_file)
    return None if source is None else source.current()
