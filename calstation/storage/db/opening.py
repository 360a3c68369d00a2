"""Opening the run database for a command: the schema made ready, then whatever the journal
kept while the database was away written to it (:func:`open_database`)."""

from __future__ import annotations

import sys

from calstation.storage.db.database import Database
from calstation.storage.db.journal import recover as recover_runs


def open_database(url: str | None = None, *, recover: bool = True,
                  read_only: bool = False, existing: bool = False) -> Database:
    """Open the database at ``url`` (default :func:`default_database_url`), schema ready.

    With ``recover``, results journalled while the database was unavailable are written now, and
    runs whose process ended without finishing them are marked ``interrupted``
    (:func:`calstation.storage.db.journal.recover`); what was done is said on standard error.
    ``read_only`` is for commands that only read: they make no database or folder (a missing
    SQLite file is a :class:`~calstation.errors.DatabaseError`), migrate nothing, and read a
    file they may not write (recovering nothing there). ``existing`` is for commands that work
    on stored runs and write (``upload``, ``resume``): a missing SQLite file is refused, not
    made.
    """
    db = Database(url, read_only=read_only, must_exist=existing)
    if read_only:
        db.check_schema()
    else:
        db.ensure_schema()
    if recover and db.writable:
        for note in recover_runs(db):
            print(f"calstation: {note}", file=sys.stderr, flush=True)
    return db
