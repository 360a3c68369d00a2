"""The run database: engine, sessions, lock waits, the schema check and one-sentence errors
(:class:`Database`); the package docstring (:mod:`calstation.storage.db`) says more."""

from __future__ import annotations

import datetime as dt
import os
import sqlite3
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from sqlalchemy import Connection, Engine, create_engine, event, inspect
from sqlalchemy.exc import IntegrityError, OperationalError, SQLAlchemyError
from sqlalchemy.orm import Session, sessionmaker

from calstation.errors import DamagedDatabase, DatabaseError

if TYPE_CHECKING:
    from alembic.config import Config
    from sqlalchemy.engine import URL
    from sqlalchemy.engine.interfaces import DBAPIConnection
from calstation.storage.db.models import (
    PARAMS,
    Artifact,
    Base,
    Calibration,
    CubeCheckRecord,
    DatabaseIdentity,
    Run,
    Station,
    StationLock,
    Step,
    utcnow,
)

__all__ = [
    "PARAMS",
    "Artifact",
    "Base",
    "Calibration",
    "CubeCheckRecord",
    "Database",
    "Run",
    "Station",
    "StationLock",
    "Step",
    "calstation_home",
    "default_database_url",
    "get_or_create_station",
    "migrations_dir",
    "utcnow",
]


def calstation_home() -> Path:
    """The folder of calstation's data: ``$CALSTATION_HOME``, else ``~/.local/share/calstation``."""
    env = os.environ.get("CALSTATION_HOME")
    if env:
        return Path(env).expanduser()
    xdg = os.environ.get("XDG_DATA_HOME")
    base = Path(xdg).expanduser() if xdg else Path.home() / ".local" / "share"
    return base / "calstation"


def default_database_url() -> str:
    """``$CALSTATION_DB_URL``, else SQLite at ``calstation_home()/calstation.db``."""
    env = os.environ.get("CALSTATION_DB_URL")
    if env:
        return env
    return f"sqlite:///{calstation_home() / 'calstation.db'}"


def migrations_dir() -> Path:
    """The Alembic script folder, shipped in the package (``calstation/storage/db/migrations``:
    an installed calstation creates and upgrades its database without its checkout)."""
    path = Path(__file__).resolve().parent / "migrations"
    if not (path / "env.py").is_file():
        raise DatabaseError(f"the database migrations are missing: {path}/env.py not found")
    return path


DEFAULT_LOCK_TIMEOUT_S = 120.0
"""How long a locked database is waited for, unless ``CALSTATION_DB_LOCK_TIMEOUT`` says."""

WAIT_NOTICE_S = 2.0
"""After this long inside one transaction, say that calstation is waiting for the database."""


def lock_timeout_s() -> float:
    """``$CALSTATION_DB_LOCK_TIMEOUT`` (seconds, ≥ 0), else :data:`DEFAULT_LOCK_TIMEOUT_S`."""
    env = os.environ.get("CALSTATION_DB_LOCK_TIMEOUT")
    if not env:
        return DEFAULT_LOCK_TIMEOUT_S
    try:
        value = float(env)
    except ValueError:
        value = -1.0
    if not 0.0 <= value <= 86_400.0:
        raise DatabaseError(
            f"CALSTATION_DB_LOCK_TIMEOUT={env!r}: expected seconds between 0 and 86400"
        )
    return value


READ_ONLY = "calstation_read_only"
"""Execution option of the engine behind :meth:`Database.session` ``(read_only=True)``."""


class ReadingSession(Session):
    """The session of :meth:`Database.session` ``(read_only=True)``: it refuses to write, since
    its transaction holds no lock to write with."""

    def flush(self, objects: Sequence[object] | None = None) -> None:
        """Refuse pending changes (an error in calstation, not in the database)."""
        if self.new or self.dirty or self.deleted:
            raise DatabaseError(
                "calstation tried to write in a read-only database session; nothing was written"
            )
        super().flush(objects)


def make_engine(url: str, lock_timeout: float | None = None) -> Engine:
    """An engine for ``url``; SQLite gets WAL mode, foreign keys, its folder created, and
    transactions that take the write lock when they begin (``BEGIN IMMEDIATE``: a transaction
    that read first can then never fail to upgrade its lock), except on connections with the
    execution option :data:`READ_ONLY`, whose transactions only read and so take no lock: in WAL
    mode they read the last commit while another process writes. A lock is waited for
    ``lock_timeout`` seconds (default :func:`lock_timeout_s`), on PostgreSQL too."""
    timeout = lock_timeout_s() if lock_timeout is None else lock_timeout
    try:
        # pre-ping: a pooled connection that a restarted server dropped is replaced, not used
        engine = create_engine(url, pool_pre_ping=not url.startswith("sqlite"))
    except (SQLAlchemyError, ImportError, ValueError) as exc:
        hint = ""
        if url.startswith("postgresql"):
            hint = " (PostgreSQL needs the driver: pip install 'calstation[postgres]')"
        raise DatabaseError(f"cannot use database URL {url!r}: {exc}{hint}") from None
    if engine.dialect.name == "sqlite":
        database = engine.url.database
        if database and database != ":memory:" and not database.startswith("file:"):
            Path(database).expanduser().parent.mkdir(parents=True, exist_ok=True)

        def connect(dbapi_connection: sqlite3.Connection, _record: object) -> None:
            dbapi_connection.isolation_level = None  # transactions are begun below
            cursor = dbapi_connection.cursor()
            cursor.execute(f"PRAGMA busy_timeout={int(timeout * 1000)}")
            try:
                _retry_locked(lambda: cursor.execute("PRAGMA journal_mode=WAL"), timeout)
            except UnicodeDecodeError:
                # SQLite's own message about a damaged schema, holding the damaged bytes
                raise sqlite3.DatabaseError("malformed database schema") from None
            cursor.execute("PRAGMA foreign_keys=ON")
            cursor.close()

        def begin(conn: Connection) -> None:
            read_only = conn.get_execution_options().get(READ_ONLY, False)
            conn.exec_driver_sql("BEGIN" if read_only else "BEGIN IMMEDIATE")

        event.listen(engine, "connect", connect)
        event.listen(engine, "begin", begin)
    elif engine.dialect.name == "postgresql":

        def pg_connect(dbapi_connection: DBAPIConnection, _record: object) -> None:
            cursor = dbapi_connection.cursor()
            cursor.execute(f"SET lock_timeout = {int(timeout * 1000)}")
            cursor.close()
            dbapi_connection.commit()

        event.listen(engine, "connect", pg_connect)
    return engine


def _retry_locked(statement: Callable[[], object], timeout: float) -> None:
    """Run ``statement`` until SQLite stops answering "database is locked", for up to
    ``timeout`` seconds. Switching a fresh database to WAL needs an exclusive lock; when two
    processes open it together each may hold a read lock the other's switch waits for, and
    SQLite then answers busy at once instead of calling the busy handler (a deadlock it
    refuses), so the wait happens here."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            statement()
            return
        except sqlite3.OperationalError as exc:
            if "locked" not in str(exc) or time.monotonic() >= deadline:
                raise
            time.sleep(0.05)


@contextmanager
def foreign_keys_off(connection: Connection) -> Iterator[None]:
    """SQLite: foreign keys off while migrating (before any transaction begins).

    A batch migration rebuilds a table (copy, drop, rename); with foreign keys on, dropping the
    old ``run`` table would cascade-delete every step, calibration and artifact row."""
    if connection.dialect.name != "sqlite":
        yield
        return
    raw = connection.connection.dbapi_connection
    if raw is None:
        raise DatabaseError("the database connection was closed before migrating")
    raw.cursor().execute("PRAGMA foreign_keys=OFF")
    try:
        yield
    finally:
        raw.cursor().execute("PRAGMA foreign_keys=ON")


def _is_lock(exc: BaseException) -> bool:
    """Whether a driver error means "locked" (SQLite busy, PostgreSQL lock timeout)."""
    orig = getattr(exc, "orig", exc)
    text = str(orig).lower()
    code = getattr(orig, "sqlstate", None) or getattr(orig, "pgcode", None)
    return (
        "database is locked" in text
        or "database is busy" in text
        or "lock timeout" in text
        or code == "55P03"
    )


_DAMAGED = ("file is not a database", "malformed", "unsupported file format",
            "could not decode to utf-8", "file is encrypted", "disk image")
"""What SQLite says of a file that is not a database, or one whose content is damaged."""


def _is_damaged(exc: BaseException) -> bool:
    """Whether a driver error means the database file is not one, or is damaged."""
    text = str(getattr(exc, "orig", None) or exc).lower()
    return isinstance(exc, UnicodeDecodeError) or any(d in text for d in _DAMAGED)


def _driver_message(exc: BaseException) -> str:
    """The driver's own first line, without SQL or parameters."""
    orig = getattr(exc, "orig", None) or exc
    text = str(orig).strip().splitlines()
    first = text[0] if text else type(orig).__name__
    return first if len(first) <= 200 else first[:200] + "…"


def alembic_config(connection: Connection | None = None, url: str | None = None) -> Config:
    """An Alembic ``Config`` for the migrations (:func:`migrations_dir`), optionally bound to an
    open ``connection``."""
    from alembic.config import Config

    cfg = Config()
    cfg.set_main_option("script_location", str(migrations_dir()))
    if url is not None:
        cfg.set_main_option("sqlalchemy.url", url.replace("%", "%%"))
    if connection is not None:
        cfg.attributes["connection"] = connection
    return cfg


SCHEMA_HEAD = "0014_cube_height_judged"
"""The newest migration's revision id, as written in ``migrations/versions`` beside this module
(a test checks that they agree). Opening a database that is at it needs no Alembic, which takes
~0.1 s to import; only a new, older or unknown database loads it."""


def head_revision() -> str:
    """The newest migration's revision id (read from the migrations by Alembic)."""
    from alembic.script import ScriptDirectory

    head = ScriptDirectory.from_config(alembic_config()).get_current_head()
    if head is None:
        raise DatabaseError("the migrations folder holds no revision")
    return head


def known_revisions() -> set[str]:
    """Every revision id of the migrations (:func:`migrations_dir`)."""
    from alembic.script import ScriptDirectory

    return {rev.revision for rev in ScriptDirectory.from_config(alembic_config()).walk_revisions()}


def _say_waiting(message: str) -> None:
    print(f"calstation: {message}", file=sys.stderr, flush=True)


_MIGRATION_LOCK_KEY = 0x63616C73  # "cals": PostgreSQL advisory lock held while migrating


def _existing(url: str) -> tuple[URL, Path] | None:
    """(the parsed URL, the file) of a SQLite file URL, which must exist (a mistyped path is a
    :class:`DatabaseError`, and nothing is made); None for any other URL."""
    from sqlalchemy.engine import make_url

    try:
        parsed = make_url(url)
    except Exception:
        return None  # make_engine says what is wrong with it
    database = parsed.database or ""
    if parsed.get_backend_name() != "sqlite" or database in ("", ":memory:") or \
            database.startswith("file:"):
        return None
    path = Path(database).expanduser()
    if not path.exists():
        raise DatabaseError(
            f"there is no database at {path}: this command works on a database that exists "
            "and makes none (a mistyped --db or $CALSTATION_DB_URL?)"
        )
    if not path.is_file():
        raise DatabaseError(f"{path} is not a database file (it is not a regular file)")
    return parsed, path


def _readable(url: str) -> tuple[str, bool]:
    """For a command that only reads: (the URL to open, whether the database may be written).

    A SQLite file must exist (:func:`_existing`); a file this process may not write (a
    read-only copy, a read-only mount) is opened read-only, as immutable when no other process
    has it open in WAL mode (no ``-wal`` file beside it: SQLite could otherwise not read it
    without writing its ``-shm``)."""
    found = _existing(url)
    if found is None:
        return url, True
    parsed, path = found
    if os.access(path, os.W_OK) and os.access(path.parent, os.W_OK):
        return url, True
    wal = path.with_name(path.name + "-wal").exists()
    options = "mode=ro" + ("" if wal else "&immutable=1")
    uri = parsed.set(database=f"file:{path.resolve()}?{options}", query={"uri": "true"})
    return uri.render_as_string(hide_password=False), False


@dataclass(frozen=True)
class _RunScope:
    """Where a run's database faults are logged and who is told of its waits."""

    db: Database
    log_path: Path
    on_wait: Callable[[str], None]


_SCOPE: ContextVar[_RunScope | None] = ContextVar("calstation_database_run", default=None)
"""The run whose thread this is (:meth:`Database.run_scope`), if any."""


class Database:
    """An opened run database: an engine plus sessions from a context manager.

    ``lock_timeout`` (seconds, default :func:`lock_timeout_s`) bounds the wait for a lock;
    ``on_wait(message)`` is told when a transaction has waited :data:`WAIT_NOTICE_S` (default:
    a line on standard error); failures are logged in full to :attr:`log_path`. ``read_only``:
    for a command that only reads, which makes nothing: a SQLite file must exist, and one this
    process may not write is opened read-only (:attr:`writable` is then False and a writing
    session is refused). ``must_exist``: for a command that works on stored runs, a SQLite
    file that is not there is refused rather than made.
    """

    def __init__(
        self,
        url: str | None = None,
        *,
        lock_timeout: float | None = None,
        on_wait: Callable[[str], None] | None = None,
        read_only: bool = False,
        must_exist: bool = False,
    ) -> None:
        self.url = url or default_database_url()
        self.read_only = read_only
        self.writable = True
        """Whether the database may be written (False: a read-only file opened to read)."""
        opened = self.url
        if read_only:
            opened, self.writable = _readable(self.url)
        elif must_exist:
            _existing(self.url)
        self.lock_timeout = lock_timeout_s() if lock_timeout is None else float(lock_timeout)
        self.engine = make_engine(opened, self.lock_timeout)
        self._sessions = sessionmaker(self.engine, expire_on_commit=False)
        self.reader: Engine = self.engine.execution_options(**{READ_ONLY: True})
        """The engine for reading only: its connections take no lock (see :func:`make_engine`)."""
        self._readers = sessionmaker(self.reader, class_=ReadingSession, expire_on_commit=False)
        self.on_wait: Callable[[str], None] = on_wait or _say_waiting
        self.log_path: Path = calstation_home() / "database.log"
        self._identity: str | None = None

    def __repr__(self) -> str:
        return f"Database({self.engine.url.render_as_string(hide_password=True)!r})"

    @property
    def display_url(self) -> str:
        """The URL without its password."""
        return str(self.engine.url.render_as_string(hide_password=True))

    # --- faults ------------------------------------------------------------------------------
    @contextmanager
    def run_scope(self, log_path: Path, on_wait: Callable[[str], None]) -> Iterator[None]:
        """Within the block, and in this thread only, this database's faults are logged to
        ``log_path`` and its waits told to ``on_wait`` (a run's folder and its operator). Other
        threads keep :attr:`log_path` and :attr:`on_wait`: in ``calstation serve`` one
        database serves every page while a run goes on."""
        token = _SCOPE.set(_RunScope(self, log_path, on_wait))
        try:
            yield
        finally:
            _SCOPE.reset(token)

    def _scope(self) -> _RunScope | None:
        scope = _SCOPE.get()
        return scope if scope is not None and scope.db is self else None

    def log(self, text: str) -> Path | None:
        """Append ``text`` (with the time) to the log of this thread's run
        (:meth:`run_scope`), else :attr:`log_path`; the path, or None if unwritable."""
        scope = self._scope()
        path = scope.log_path if scope is not None else self.log_path
        try:
            if not self.read_only:
                path.parent.mkdir(parents=True, exist_ok=True)
            with path.open("a", encoding="utf-8") as f:
                f.write(f"{dt.datetime.now(dt.UTC).isoformat()} {self.display_url}\n{text}\n\n")
        except OSError:
            return None
        return path

    def _damaged_sentence(self, exc: BaseException, where: str) -> str:
        """What to say of a file that is not a database or is damaged, and what to do."""
        text = str(getattr(exc, "orig", None) or exc).lower()
        said = next((d for d in _DAMAGED if d in text), "malformed")
        what = ("is not a database" if said in ("file is not a database", "file is encrypted")
                else f"is damaged (SQLite: {said})")
        name = self.engine.url.database or self.display_url
        return (
            f"the database file {name} {what}: give calstation the right file (--db or "
            "$CALSTATION_DB_URL), or move this one aside, and restore it from a backup if it "
            f"held runs (calstation creates a new, empty database where none is){where}"
        )

    def error(self, exc: BaseException, doing: str) -> DatabaseError:
        """One clear sentence for a failed database operation; the details go to the log."""
        logged = self.log(f"{doing}: {type(exc).__name__}: {exc}")
        where = f" (details in {logged})" if logged else ""
        if _is_damaged(exc):
            return DamagedDatabase(self._damaged_sentence(exc, where))
        if _is_lock(exc):
            return DatabaseError(
                f"the database {self.display_url} stayed locked by another process for "
                f"{self.lock_timeout:g} s while {doing}; calstation gave up{where}"
            )
        if isinstance(exc, IntegrityError):
            return DatabaseError(
                f"the database {self.display_url} refused a write while {doing}: "
                f"{_driver_message(exc)}{where}"
            )
        if isinstance(exc, OperationalError):
            return DatabaseError(
                f"the database {self.display_url} is unavailable while {doing}: "
                f"{_driver_message(exc)}{where}"
            )
        return DatabaseError(
            f"database error on {self.display_url} while {doing}: {_driver_message(exc)}{where}"
        )

    @contextmanager
    def _waiting_notice(self) -> Iterator[None]:
        scope = self._scope()  # the timer's thread is not this run's: who to tell is taken now
        notify = scope.on_wait if scope is not None else self.on_wait
        timer = threading.Timer(
            WAIT_NOTICE_S,
            lambda: notify(
                f"waiting for the database {self.display_url} (locked by another process?); "
                f"up to {self.lock_timeout:g} s (CALSTATION_DB_LOCK_TIMEOUT)"
            ),
        )
        timer.daemon = True
        timer.start()
        try:
            yield
        finally:
            timer.cancel()

    # --- sessions ----------------------------------------------------------------------------
    @contextmanager
    def session(self, doing: str = "writing", *, read_only: bool = False) -> Iterator[Session]:
        """A session that commits on success and rolls back on error.

        A lock is waited for (bounded by :attr:`lock_timeout`, announced through
        :attr:`on_wait`); a database failure is a :class:`DatabaseError` of one sentence. A
        ``read_only`` session must not write: on SQLite it takes no lock, so it never waits for
        a run that is writing (and never holds one up); it reads the last commit.
        """
        if not read_only and not self.writable:
            raise DatabaseError(
                f"the database {self.display_url} is a file calstation may only read here; "
                f"nothing was written while {doing}"
            )
        session = (self._readers if read_only else self._sessions)()
        try:
            with self._waiting_notice():
                yield session
                session.commit()
        except SQLAlchemyError as exc:
            session.rollback()
            raise self.error(exc, doing) from exc
        except OverflowError:  # a number the database cannot hold (an id past 64 bits)
            session.rollback()
            raise DatabaseError(
                f"a number too large for the database {self.display_url} while {doing}: its "
                "integers hold at most 2^63 − 1"
            ) from None
        except BaseException:
            session.rollback()
            raise
        finally:
            session.close()

    def current_revision(self) -> str | None:
        """The revision the database is at (None when it was never migrated)."""
        from alembic.runtime.migration import MigrationContext

        try:
            with self.reader.connect() as conn:
                return MigrationContext.configure(conn).get_current_revision()
        except SQLAlchemyError as exc:
            raise self.error(exc, "opening it") from None

    def _at_head(self) -> bool:
        """Whether the database is at :data:`SCHEMA_HEAD`, read from Alembic's version table
        without loading Alembic. False for a new database, one at another revision or one that
        cannot be read: :meth:`ensure_schema`'s full check then says which."""
        from sqlalchemy import text

        try:
            with self.reader.connect() as conn:
                rows = conn.execute(text("SELECT version_num FROM alembic_version")).all()
        except SQLAlchemyError:
            return False
        return [r[0] for r in rows] == [SCHEMA_HEAD]

    def _migrate(self, action: str, revision: str) -> tuple[str | None, str]:
        from alembic import command
        from alembic.util import CommandError

        before = self._check_known(self.current_revision())
        try:
            with self.engine.connect() as conn, foreign_keys_off(conn), conn.begin():
                getattr(command, action)(alembic_config(conn), revision)
        except SQLAlchemyError as exc:
            raise self.error(exc, f"migrating it to {revision}") from None
        except CommandError as exc:
            raise DatabaseError(f"cannot migrate {self.display_url} to {revision}: {exc}") from None
        return before, self.current_revision() or ""

    def upgrade(self, revision: str = "head") -> tuple[str | None, str]:
        """Apply migrations up to ``revision``; returns (revision before, revision after)."""
        return self._migrate("upgrade", revision)

    def downgrade(self, revision: str) -> tuple[str | None, str]:
        """Undo migrations down to ``revision``, keeping every row; (before, after)."""
        return self._migrate("downgrade", revision)

    def _check_known(self, current: str | None) -> str | None:
        if current is not None and current not in known_revisions():
            raise DatabaseError(
                f"the database {self.display_url} is at revision {current!r}, which this "
                f"calstation does not know (its newest is {head_revision()}): it was migrated "
                "by a newer calstation; use that version, or another database (--db)"
            )
        return current

    def check_schema(self) -> None:
        """For reading only: :class:`DatabaseError` unless the database is at the newest
        revision (nothing is migrated or made; an empty file is no calstation database)."""
        if self._at_head():
            return
        current = self._check_known(self.current_revision())
        if current is None:
            raise DatabaseError(
                f"the database {self.display_url} holds no calstation tables: this command only "
                "reads (a run, or `calstation db upgrade`, makes them)"
            )
        raise DatabaseError(
            f"the database {self.display_url} is at revision {current}, calstation needs "
            f"{head_revision()}: run `calstation db upgrade`"
        )

    def ensure_schema(self) -> None:
        """Migrate a brand-new (empty) database; refuse one that is behind or ahead of the code.

        The check and the migration run in one transaction holding the write lock (SQLite) or an
        advisory lock (PostgreSQL), so two processes opening a fresh database together do not
        both create the tables. Raises :class:`DatabaseError` telling to run ``calstation db
        upgrade`` when the database holds tables but is behind, and naming an unknown revision.
        """
        if self._at_head():
            return
        head = head_revision()
        if self._check_known(self.current_revision()) == head:
            return
        from alembic import command
        from alembic.runtime.migration import MigrationContext

        try:
            with self.engine.connect() as conn, foreign_keys_off(conn), conn.begin():
                if conn.dialect.name == "postgresql":
                    conn.exec_driver_sql(f"SELECT pg_advisory_xact_lock({_MIGRATION_LOCK_KEY})")
                current = MigrationContext.configure(conn).get_current_revision()
                if current == head:
                    return  # another process migrated it while this one waited
                tables = set(inspect(conn).get_table_names())
                if current is None and not tables & set(Base.metadata.tables):
                    command.upgrade(alembic_config(conn), "head")
                    return
        except SQLAlchemyError as exc:
            raise self.error(exc, "creating its tables") from None
        self._check_known(current)
        raise DatabaseError(
            f"the database {self.display_url} is at revision {current or 'none'}, calstation "
            f"needs {head}: run `calstation db upgrade`"
        )

    def dispose(self) -> None:
        """Close every pooled connection."""
        self.engine.dispose()

    @property
    def identity(self) -> str:
        """This database's identity (:class:`~calstation.storage.db.models.DatabaseIdentity`),
        which names its run folders and shared copies: read once, and given now to a database
        whose tables were made without the migrations."""
        if self._identity is None:
            from sqlalchemy import select

            with self.session("reading the database's identity", read_only=True) as s:
                uid = s.scalars(select(DatabaseIdentity.uid).order_by(DatabaseIdentity.id)).first()
            if uid is None:
                import uuid

                with self.session("giving the database its identity") as s:
                    uid = s.scalars(select(DatabaseIdentity.uid)).first()
                    if uid is None:
                        uid = uuid.uuid4().hex[:12]
                        s.add(DatabaseIdentity(uid=uid))
            self._identity = uid
        return self._identity


def get_or_create_station(db: Database, name: str) -> int:
    """The id of station ``name``, created if new. Safe when several processes start runs on a
    new station at once: a process that loses the race to insert it reads the winner's row."""
    from sqlalchemy import select

    for attempt in range(3):
        try:
            with db.session("registering the station") as s:
                found = s.scalars(select(Station.id).where(Station.name == name)).first()
                if found is not None:
                    return int(found)
                row = Station(name=name)
                s.add(row)
                s.flush()
                return int(row.id)
        except DatabaseError as exc:
            if not isinstance(exc.__cause__, IntegrityError) or attempt == 2:
                raise
    raise DatabaseError(f"could not register station {name!r}")  # not reached
