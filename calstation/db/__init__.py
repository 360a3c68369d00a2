"""The run database: where it lives, how to open it, and its migrations.

By default the database is SQLite at ``$CALSTATION_HOME/calstation.db`` (``CALSTATION_HOME``
defaults to ``$XDG_DATA_HOME/calstation``, i.e. ``~/.local/share/calstation``), opened in WAL
mode. ``CALSTATION_DB_URL`` or a ``--db URL`` option selects another database, e.g.
``postgresql+psycopg://user@host/calstation`` for a fleet of stations (``pip install
calstation[postgres]``). The schema is managed by the Alembic migrations in ``migrations/``;
``calstation db upgrade`` applies them, and a fresh, empty database is migrated automatically
when first opened.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from sqlalchemy import Engine, create_engine, event, inspect
from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Session, sessionmaker

from ..errors import DatabaseError
from .models import (
    PARAMS,
    Artifact,
    Base,
    Calibration,
    CubeCheckRecord,
    Run,
    Station,
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
    "Step",
    "calstation_home",
    "default_database_url",
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
    """The Alembic script folder (``migrations/`` beside the package)."""
    path = Path(__file__).resolve().parents[2] / "migrations"
    if not (path / "env.py").is_file():
        raise DatabaseError(f"the database migrations are missing: {path}/env.py not found")
    return path


def _sqlite_pragmas(dbapi_connection: Any, _record: Any) -> None:
    cursor = dbapi_connection.cursor()
    cursor.execute("PRAGMA journal_mode=WAL")
    cursor.execute("PRAGMA foreign_keys=ON")
    cursor.execute("PRAGMA busy_timeout=10000")
    cursor.close()


def make_engine(url: str) -> Engine:
    """An engine for ``url``; SQLite gets WAL mode, foreign keys and its folder created."""
    try:
        engine = create_engine(url)
    except (SQLAlchemyError, ImportError, ValueError) as exc:
        hint = ""
        if url.startswith("postgresql"):
            hint = " (PostgreSQL needs the driver: pip install 'calstation[postgres]')"
        raise DatabaseError(f"cannot use database URL {url!r}: {exc}{hint}") from None
    if engine.dialect.name == "sqlite":
        database = engine.url.database
        if database and database != ":memory:" and not database.startswith("file:"):
            Path(database).expanduser().parent.mkdir(parents=True, exist_ok=True)
        event.listen(engine, "connect", _sqlite_pragmas)
    return engine


def alembic_config(connection: Any = None, url: str | None = None) -> Any:
    """An Alembic ``Config`` for ``migrations/``, optionally bound to an open ``connection``."""
    from alembic.config import Config

    cfg = Config()
    cfg.set_main_option("script_location", str(migrations_dir()))
    if url is not None:
        cfg.set_main_option("sqlalchemy.url", url.replace("%", "%%"))
    if connection is not None:
        cfg.attributes["connection"] = connection
    return cfg


def head_revision() -> str:
    """The newest migration's revision id."""
    from alembic.script import ScriptDirectory

    head = ScriptDirectory.from_config(alembic_config()).get_current_head()
    if head is None:
        raise DatabaseError("the migrations folder holds no revision")
    return head


class Database:
    """An opened run database: an engine plus sessions from a context manager."""

    def __init__(self, url: str | None = None) -> None:
        self.url = url or default_database_url()
        self.engine = make_engine(self.url)
        self._sessions = sessionmaker(self.engine, expire_on_commit=False)

    def __repr__(self) -> str:
        return f"Database({self.engine.url.render_as_string(hide_password=True)!r})"

    @contextmanager
    def session(self) -> Iterator[Session]:
        """A session that commits on success and rolls back on error."""
        session = self._sessions()
        try:
            yield session
            session.commit()
        except SQLAlchemyError as exc:
            session.rollback()
            raise DatabaseError(f"database error on {self!r}: {exc}") from exc
        except BaseException:
            session.rollback()
            raise
        finally:
            session.close()

    def current_revision(self) -> str | None:
        """The revision the database is at (None when it was never migrated)."""
        from alembic.runtime.migration import MigrationContext

        try:
            with self.engine.connect() as conn:
                return MigrationContext.configure(conn).get_current_revision()
        except SQLAlchemyError as exc:
            raise DatabaseError(f"cannot open the database {self!r}: {exc}") from None

    def upgrade(self, revision: str = "head") -> tuple[str | None, str]:
        """Apply migrations up to ``revision``; returns (revision before, revision after)."""
        from alembic import command

        before = self.current_revision()
        try:
            with self.engine.begin() as conn:
                command.upgrade(alembic_config(conn), revision)
        except SQLAlchemyError as exc:
            raise DatabaseError(f"migrating {self!r} failed: {exc}") from None
        return before, self.current_revision() or ""

    def ensure_schema(self) -> None:
        """Migrate a brand-new (empty) database; refuse one that is behind the code.

        Raises :class:`DatabaseError` telling to run ``calstation db upgrade`` when the database
        holds tables but is not at the newest revision.
        """
        current = self.current_revision()
        head = head_revision()
        if current == head:
            return
        if current is None:
            with self.engine.connect() as conn:
                tables = set(inspect(conn).get_table_names())
            if not tables & set(Base.metadata.tables):
                self.upgrade()
                return
        raise DatabaseError(
            f"the database {self!r} is at revision {current or 'none'}, calstation needs {head}: "
            "run `calstation db upgrade`"
        )

    def dispose(self) -> None:
        """Close every pooled connection."""
        self.engine.dispose()


def open_database(url: str | None = None) -> Database:
    """Open the database at ``url`` (default :func:`default_database_url`), schema ready."""
    db = Database(url)
    db.ensure_schema()
    return db
