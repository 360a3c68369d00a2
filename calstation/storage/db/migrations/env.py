"""Alembic environment of calstation's run database.

Uses the connection in ``config.attributes["connection"]`` when one is given (calstation's own
``Database.upgrade`` and the tests pass theirs, with SQLite's foreign keys already off: see
``calstation.storage.db.foreign_keys_off``); otherwise connects to ``-x url=...``, the
``sqlalchemy.url`` option, ``CALSTATION_DB_URL`` or the default SQLite file.
"""

from __future__ import annotations

from alembic import context

from calstation.storage.db import default_database_url, foreign_keys_off, make_engine
from calstation.storage.db.models import Base

config = context.config
target_metadata = Base.metadata


def _url() -> str:
    return (
        context.get_x_argument(as_dictionary=True).get("url")
        or config.get_main_option("sqlalchemy.url")
        or default_database_url()
    )


def _configure(connection: object) -> None:
    context.configure(
        connection=connection,
        target_metadata=target_metadata,
        render_as_batch=True,
        compare_type=True,
    )


def run_migrations_offline() -> None:
    """Emit SQL for ``alembic upgrade --sql``."""
    context.configure(
        url=_url(),
        target_metadata=target_metadata,
        literal_binds=True,
        render_as_batch=True,
        compare_type=True,
    )
    with context.begin_transaction():
        context.run_migrations()


def run_migrations_online() -> None:
    """Migrate through the given connection, or one opened here."""
    connection = config.attributes.get("connection")
    if connection is not None:
        _configure(connection)
        with context.begin_transaction():
            context.run_migrations()
        return
    engine = make_engine(_url())
    # SQLite: foreign keys off while tables are rebuilt, or dropping the old table would
    # cascade-delete the rows that reference it (calstation's Database does the same)
    with engine.connect() as conn, foreign_keys_off(conn), conn.begin():
        _configure(conn)
        with context.begin_transaction():
            context.run_migrations()
    engine.dispose()


if context.is_offline_mode():
    run_migrations_offline()
else:
    run_migrations_online()
