"""Recordings on shared storage: a run's files copied to where a fleet keeps them, and read back
from there, always checked against the sha256 the database holds.

A location is a local path or an fsspec URL (``file:///srv/recordings/…``,
``s3://bucket/prefix/…``, ``memory://…``). ``s3://`` takes its credentials and endpoint from the
environment as every AWS tool does (``AWS_ACCESS_KEY_ID``, ``AWS_SECRET_ACCESS_KEY``,
``AWS_ENDPOINT_URL`` or ``FSSPEC_S3_ENDPOINT_URL`` for a non-AWS server); it needs ``s3fs``
(``pip install 'calstation[s3]'``).

:func:`upload` copies a file to a location: under a ``.partial`` name first, read back and
checked against the sha256, then moved into place and read back once more through new
connections (past any cache of the file system that wrote it), so a location never holds a file
that is not the recording; a location that holds another file already is refused, never
replaced. A store that does not answer within ``$CALSTATION_UPLOAD_TIMEOUT`` seconds (default
30, for connecting and for each read or write) is :class:`StoreUnanswered`, a sentence naming
its endpoint. It is resumable: a file already in place with the right sha256 is not sent again,
and on a file system that can append (local, memory) a ``.partial`` left by an interrupted copy is
continued after its bytes are checked; an object store writes whole objects, so there the file
is sent again. The source is only ever read.

:func:`local_copy` gives a readable local file for a stored recording: its own path when that
file is there and unchanged, else its shared copy, fetched into a cache named by the sha256
(shared by every run that stored the same bytes) and checked.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from calstation.atomic import atomic_output, write_atomic
from calstation.errors import OutputError, RecordingError

if TYPE_CHECKING:
    from fsspec import AbstractFileSystem

CHUNK = 8 << 20
"""Bytes per read and write while copying or hashing (8 MiB)."""

_URL = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*://")


class SharedStorageError(RecordingError):
    """A shared location cannot be reached, written, or holds other bytes than expected."""


class StoreUnanswered(SharedStorageError):
    """The shared store did not answer within :func:`transfer_timeout_s`."""


TIMEOUT_ENV = "CALSTATION_UPLOAD_TIMEOUT"
DEFAULT_TIMEOUT_S = 30.0
"""Seconds a shared store has to accept a connection, and to answer each read or write."""


def transfer_timeout_s() -> float:
    """``$CALSTATION_UPLOAD_TIMEOUT`` (seconds, > 0 and at most an hour), else
    :data:`DEFAULT_TIMEOUT_S`."""
    text = os.environ.get(TIMEOUT_ENV)
    if not text:
        return DEFAULT_TIMEOUT_S
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not 0.0 < value <= 3600.0:
        raise SharedStorageError(f"{TIMEOUT_ENV}={text!r}: expected seconds, more than 0 and "
                                 "at most 3600")
    return value


def is_url(location: str) -> bool:
    """Whether ``location`` is an fsspec URL (``scheme://…``) rather than a local path."""
    return bool(_URL.match(location))


def endpoint(location: str) -> str:
    """Who answers for ``location``, in words: the S3 endpoint (``AWS_ENDPOINT_URL``, else AWS
    itself) for ``s3://``, the scheme and host of another URL, the folder of a local path."""
    if not is_url(location):
        return f"the folder {location}"
    scheme, _, rest = location.partition("://")
    host = rest.split("/", 1)[0]
    if scheme in ("s3", "s3a"):
        url = next((os.environ[k] for k in ("AWS_ENDPOINT_URL_S3", "AWS_ENDPOINT_URL",
                                            "FSSPEC_S3_ENDPOINT_URL") if os.environ.get(k)),
                   None)
        return f"the S3 endpoint {url} (bucket {host})" if url else f"AWS S3 (bucket {host})"
    return f"{scheme}://{host}"


def _options(protocol: str, timeout: float) -> dict[str, object]:
    """The file system's options that bound its waits, for the protocols that take them."""
    if protocol in ("s3", "s3a"):
        return {"config_kwargs": {"connect_timeout": timeout, "read_timeout": timeout,
                                  "retries": {"max_attempts": 2, "mode": "standard"}}}
    if protocol in ("sftp", "ssh"):
        return {"timeout": timeout}
    return {}


def unanswered(exc: BaseException) -> bool:
    """Whether ``exc`` (or what caused it) is a time-out of the network."""
    seen: BaseException | None = exc
    for _ in range(10):
        if seen is None:
            return False
        if isinstance(seen, TimeoutError) or "Timeout" in type(seen).__name__:
            return True
        seen = seen.__cause__ or seen.__context__
    return False


def timed_out(location: str) -> StoreUnanswered:
    """The sentence for a store that did not answer."""
    return StoreUnanswered(
        f"{endpoint(location)} did not answer within {transfer_timeout_s():g} s "
        f"({TIMEOUT_ENV}) for {location}: nothing was changed there or in the database"
    )


def filesystem(location: str, *, fresh: bool = False) -> tuple[AbstractFileSystem, str]:
    """(the fsspec file system, the path within it) of ``location``; a clear error when its
    protocol is unknown or its package is missing (``s3fs`` for ``s3://``). Connections and
    reads wait at most :func:`transfer_timeout_s` (S3: one retry). ``fresh``: a file system
    of its own, on new connections (to read back what was written, past any cache)."""
    import fsspec

    protocol = location.split("://", 1)[0] if is_url(location) else "file"
    try:
        fs, path = fsspec.core.url_to_fs(location, skip_instance_cache=fresh,
                                         **_options(protocol, transfer_timeout_s()))
        if protocol in ("s3", "s3a"):
            fs.retries = 1  # s3fs's own retries, on top of botocore's
        return fs, str(path)
    except ImportError as exc:
        raise SharedStorageError(
            f"{location}: {exc} (s3:// needs s3fs: pip install 'calstation[s3]')"
        ) from None
    except (ValueError, OSError) as exc:
        raise SharedStorageError(f"{location}: {exc}") from None


def join(base: str, *parts: str) -> str:
    """``base`` (a URL or path) with ``parts`` appended, one ``/`` between each."""
    return "/".join([base.rstrip("/"), *(p.strip("/") for p in parts)])


def sha256_of(fs: AbstractFileSystem, path: str) -> str:
    """sha256 (hex) of the bytes of ``path`` on ``fs``."""
    h = hashlib.sha256()
    with fs.open(path, "rb") as f:
        for chunk in iter(lambda: f.read(CHUNK), b""):
            h.update(chunk)
    return h.hexdigest()


def _prefix_sha256(path: Path, size: int) -> str:
    """sha256 of the first ``size`` bytes of the local file ``path``."""
    h = hashlib.sha256()
    left = size
    with path.open("rb") as f:
        while left > 0:
            chunk = f.read(min(CHUNK, left))
            if not chunk:
                break
            h.update(chunk)
            left -= len(chunk)
    return h.hexdigest()


@dataclass(frozen=True)
class Uploaded:
    """What :func:`upload` did: ``location`` now holds the file (checked); ``sent`` bytes went
    over (0 when it was there already); ``resumed_from`` the bytes of an earlier ``.partial``
    that were kept."""

    location: str
    sent: int
    resumed_from: int = 0


def _appendable(fs: AbstractFileSystem) -> bool:
    """Whether ``fs`` can append to a file (so an interrupted copy can be continued)."""
    protocols = fs.protocol if isinstance(fs.protocol, tuple | list) else (fs.protocol,)
    return bool({"file", "local", "memory"} & set(protocols))


def upload(source: Path, location: str, sha256: str) -> Uploaded:
    """Copy the local file ``source`` (whose sha256 is ``sha256``) to ``location`` and check it
    there; see the module docstring. :class:`SharedStorageError` when it cannot be done; the
    source is never changed."""
    fs, path = filesystem(location)
    size = source.stat().st_size
    try:
        if fs.exists(path):
            found = _read_back(location, size)
            if found == sha256:
                return Uploaded(location, 0)
            raise SharedStorageError(
                f"{location} holds another file already ("
                + (f"sha256 {found[:12]}…" if found else f"{fs.size(path)} bytes")
                + f", not the {size} bytes of {source}): calstation never replaces an object "
                "it did not write; nothing was sent"
            )
        partial = path + ".partial"
        kept = _resumable_part(fs, partial, source, size)
        parent = path.rsplit("/", 1)[0]
        if _appendable(fs) and parent and parent != path:
            # folders of a file system; an object store has none (and its bucket is the
            # store's to create, not calstation's)
            fs.makedirs(parent, exist_ok=True)
        with source.open("rb") as src, fs.open(partial, "ab" if kept else "wb") as dst:
            src.seek(kept)
            for chunk in iter(lambda: src.read(CHUNK), b""):
                dst.write(chunk)
        found = sha256_of(fs, partial)
        if found != sha256:
            with contextlib.suppress(OSError, FileNotFoundError):
                fs.rm(partial)
            raise SharedStorageError(
                f"{location}: the copy reads back with sha256 {found[:12]}…, not "
                f"{sha256[:12]}…; it was removed (the local file {source} is kept)"
            )
        fs.mv(partial, path)
        again = _read_back(location, size)
        if again != sha256:
            raise SharedStorageError(
                f"{location}: the copy reads back from a new connection as "
                + (f"sha256 {again[:12]}…" if again else "missing, or of another size")
                + f", not {sha256[:12]}…; its location is not stored (the local file {source} "
                "is kept)"
            )
    except SharedStorageError:
        raise
    except Exception as exc:  # any file system's failure: the local copy stays as it was
        if unanswered(exc):
            raise timed_out(location) from None
        raise SharedStorageError(
            f"could not copy {source} to {location}: {type(exc).__name__}: {exc}"
        ) from None
    return Uploaded(location, size - kept, kept)


def _read_back(location: str, size: int) -> str | None:
    """The sha256 of the file at ``location`` read through a file system of its own (new
    connections, no cache), or None when it is not there or not ``size`` bytes long."""
    fs, path = filesystem(location, fresh=True)
    try:
        found = fs.size(path)
    except FileNotFoundError:
        return None
    return sha256_of(fs, path) if found == size else None


def _resumable_part(fs: AbstractFileSystem, partial: str, source: Path, size: int) -> int:
    """How many bytes of an earlier ``.partial`` copy can be kept: all of them when the file
    system appends and they are the source's first bytes, else none (it is removed)."""
    if not fs.exists(partial):
        return 0
    have = int(fs.size(partial) or 0)
    if _appendable(fs) and 0 < have <= size and (
        sha256_of(fs, partial) == _prefix_sha256(source, have)
    ):
        return have
    fs.rm(partial)
    return 0


@dataclass(frozen=True)
class StoredFile:
    """A file as the database stores it: its local ``path``, where its shared copy is
    (``location``, None when there is none), its ``sha256`` and ``size_bytes``."""

    path: str
    sha256: str
    size_bytes: int
    location: str | None = None


def cache_dir() -> Path:
    """Where shared copies are fetched to: ``$CALSTATION_CACHE``, else
    ``$CALSTATION_HOME/cache`` (``~/.local/share/calstation/cache``)."""
    env = os.environ.get("CALSTATION_CACHE")
    if env:
        return Path(env).expanduser()
    home = os.environ.get("CALSTATION_HOME")
    if home:
        return Path(home).expanduser() / "cache"
    xdg = os.environ.get("XDG_DATA_HOME")
    base = Path(xdg).expanduser() if xdg else Path.home() / ".local" / "share"
    return base / "calstation" / "cache"


def _local_sha256(path: Path) -> str:
    from calstation.recordings.runfolder import file_sha256

    return file_sha256(path)


def local_copy(stored: StoredFile, cache: Path | None = None) -> Path:
    """A local file holding exactly ``stored``'s bytes: its path when that file is there and
    unchanged, else its shared copy fetched into ``cache`` (default :func:`cache_dir`) and
    checked. :class:`SharedStorageError` saying what is wrong with each place tried: missing,
    changed (sha256), unreachable."""
    problems: list[str] = []
    path = Path(stored.path)
    if is_url(stored.path):
        problems.append(f"{stored.path} is not a local file")
    elif not path.is_file():
        problems.append(f"{path} is missing")
    else:
        digest = _local_sha256(path)
        if digest == stored.sha256:
            return path
        problems.append(
            f"{path} changed since it was stored (sha256 {digest[:12]}… now, "
            f"{stored.sha256[:12]}… stored)"
        )
    if stored.location:
        try:
            return fetch(stored.location, stored.sha256, cache)
        except SharedStorageError as exc:
            problems.append(str(exc))
    raise SharedStorageError("; ".join(problems))


def fetch(location: str, sha256: str, cache: Path | None = None) -> Path:
    """The file at ``location`` as a local file whose sha256 is ``sha256``: a local path is
    checked in place; a URL is copied into ``cache`` (once: the copy is named by its sha256 and
    re-used while the source's fsspec key is unchanged) and checked."""
    if not is_url(location) or location.startswith("file://"):
        path = Path(location.removeprefix("file://"))
        if not path.is_file():
            raise SharedStorageError(f"{location} is missing")
        digest = _local_sha256(path)
        if digest != sha256:
            raise SharedStorageError(
                f"{location} holds other bytes than stored (sha256 {digest[:12]}… there, "
                f"{sha256[:12]}… stored)"
            )
        return path
    fs, path_in = filesystem(location)
    target = (cache or cache_dir()) / "recordings" / sha256[:2] / (sha256 + Path(path_in).suffix)
    stamp = target.with_name(target.name + ".source")
    try:
        if not fs.exists(path_in):
            raise SharedStorageError(f"{location} is missing")
        key = f"{location}\n{fs.ukey(path_in)}"
        if target.is_file() and stamp.is_file() and stamp.read_text() == key:
            return target
        with atomic_output(target, "cached copy", make_parents=True) as tmp:
            h = hashlib.sha256()
            with fs.open(path_in, "rb") as src, tmp.open("wb") as dst:
                for chunk in iter(lambda: src.read(CHUNK), b""):
                    h.update(chunk)
                    dst.write(chunk)
            if h.hexdigest() != sha256:
                raise SharedStorageError(
                    f"{location} holds other bytes than stored (sha256 {h.hexdigest()[:12]}… "
                    f"there, {sha256[:12]}… stored)"
                )
        write_atomic(stamp, key, "cache stamp")
    except (SharedStorageError, OutputError):
        raise
    except Exception as exc:
        if unanswered(exc):
            raise timed_out(location) from None
        raise SharedStorageError(f"cannot read {location}: {type(exc).__name__}: {exc}") from None
    return target
