"""A throw-away PostgreSQL server from Debian's ``postgresql`` binaries (installed by
``scripts/postgres-for-tests.sh``), in a temporary folder, listening on 127.0.0.1 only: for the
database tests (the ``postgres_url`` fixture of ``tests/conftest.py``) and the fleet
benchmark."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


class NoPostgres(RuntimeError):
    """No server can be started here (no binaries, or no user to run them as)."""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _bindir() -> Path:
    for candidate in sorted(Path("/usr/lib/postgresql").glob("*/bin"), reverse=True):
        if (candidate / "initdb").exists():
            return candidate
    found = shutil.which("initdb")
    if found:
        return Path(found).parent
    raise NoPostgres("no PostgreSQL server installed (Debian: apt-get install postgresql)")


def _as_postgres(folder: Path) -> list[str]:
    """The command prefix that runs the server's binaries as user ``postgres`` when this is
    root (PostgreSQL refuses to run as root)."""
    if os.geteuid() != 0:
        return []
    runuser = shutil.which("runuser")
    try:
        import pwd

        pw = pwd.getpwnam("postgres")
    except KeyError:
        pw = None
    if runuser is None or pw is None:
        raise NoPostgres("running as root without a postgres user to start the server as")
    os.chown(folder, pw.pw_uid, pw.pw_gid)
    return [runuser, "-u", "postgres", "--"]


@contextmanager
def throwaway_postgres() -> Iterator[str]:
    """Start a private server; yields its URL (``postgresql+psycopg://…/postgres``); stops it
    and deletes its folder on leaving. :class:`NoPostgres` when it cannot be started."""
    bindir = _bindir()
    folder = Path(tempfile.mkdtemp(prefix="calstation-pg-"))
    try:
        prefix = _as_postgres(folder)
    except NoPostgres:
        shutil.rmtree(folder, ignore_errors=True)
        raise
    data, port = folder / "data", _free_port()
    try:
        subprocess.run([*prefix, str(bindir / "initdb"), "-D", str(data), "-U", "calstation",
                        "--auth=trust", "-E", "UTF8"], check=True, capture_output=True,
                       timeout=120)
        subprocess.run([*prefix, str(bindir / "pg_ctl"), "-D", str(data), "-w", "-t", "60",
                        "-l", str(folder / "log"), "-o",
                        f"-p {port} -k {folder} -c listen_addresses=127.0.0.1", "start"],
                       check=True, capture_output=True, timeout=120)
    except (subprocess.SubprocessError, OSError) as exc:
        shutil.rmtree(folder, ignore_errors=True)
        raise NoPostgres(f"could not start a PostgreSQL server: {exc}") from None
    try:
        yield f"postgresql+psycopg://calstation@127.0.0.1:{port}/postgres"
    finally:
        subprocess.run([*prefix, str(bindir / "pg_ctl"), "-D", str(data), "-m", "immediate",
                        "stop"], capture_output=True, timeout=60)
        shutil.rmtree(folder, ignore_errors=True)
