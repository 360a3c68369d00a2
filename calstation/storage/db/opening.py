"""Opening the run database for a command: the schema made ready, then whatever the journal
kept while the database was away written to it (:func:`open_database`)."""

from __future__ import annotations

import sys

from calstation.storage.db.database import Database
from calstation.storage.db.journal import recover as recover_runs


def open_database(url: str | None = None, *, recover: bool = True) -> Database:
    """Open the database at ``url`` (default :func:`default_database_url`), schema ready.

    With ``recover``, results journalled while the database was unavailable are written now, and
    runs whose process ended without finishing them are marked ``interrupted``
    (:func:`calstation.storage.db.journal.recover`); what was done is said on standard error.
    """
    db = Database(url)
    db.ensure_schema()
    if recover:
        for note in recover_runs(db):
            print(f"calstation: {note}", file=sys.stderr, flush=True)
    return db
