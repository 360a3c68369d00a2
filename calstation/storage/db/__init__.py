"""The run database: where it lives, how to open it, and its migrations.

By default the database is SQLite at ``$CALSTATION_HOME/calstation.db`` (``CALSTATION_HOME``
defaults to ``$XDG_DATA_HOME/calstation``, i.e. ``~/.local/share/calstation``), opened in WAL
mode. ``CALSTATION_DB_URL`` or a ``--db URL`` option selects another database, e.g.
``postgresql+psycopg://user@host/calstation`` for a fleet of stations (``pip install
calstation[postgres]``). The schema is managed by the Alembic migrations shipped in the package
(``calstation/storage/db/migrations/``);
``calstation db upgrade`` applies them, and a fresh, empty database is migrated automatically
when first opened (by one process at a time: concurrent first runs do not race).

Faults: a locked database is waited for (``CALSTATION_DB_LOCK_TIMEOUT`` seconds, default 120; a note
on standard error says so after 2 s), then reported in one sentence; the SQL and its parameters go
only to the log file :attr:`Database.log_path` (``database.log`` in the run folder during a run,
else in ``$CALSTATION_HOME``). A result that cannot be written is kept in the run folder's journal
(:mod:`calstation.storage.db.journal`) and written by the next command that opens the database.
"""

from __future__ import annotations

from calstation.storage.db.database import (
    DEFAULT_LOCK_TIMEOUT_S as DEFAULT_LOCK_TIMEOUT_S,
    READ_ONLY as READ_ONLY,
    SCHEMA_HEAD as SCHEMA_HEAD,
    WAIT_NOTICE_S as WAIT_NOTICE_S,
    Database as Database,
    ReadingSession as ReadingSession,
    alembic_config as alembic_config,
    calstation_home as calstation_home,
    default_database_url as default_database_url,
    foreign_keys_off as foreign_keys_off,
    get_or_create_station as get_or_create_station,
    head_revision as head_revision,
    known_revisions as known_revisions,
    lock_timeout_s as lock_timeout_s,
    make_engine as make_engine,
    migrations_dir as migrations_dir,
)
from calstation.storage.db.models import (
    PARAMS as PARAMS,
    Artifact as Artifact,
    Base as Base,
    Calibration as Calibration,
    Campaign as Campaign,
    CampaignRun as CampaignRun,
    CubeCheckRecord as CubeCheckRecord,
    Run as Run,
    RunStatus as RunStatus,
    Station as Station,
    StationLock as StationLock,
    Step as Step,
    StepStatus as StepStatus,
    utcnow as utcnow,
)
from calstation.storage.db.opening import open_database as open_database
