"""A finished run's files copied to the fleet's shared store, and where they went recorded.

The store is ``$CALSTATION_RECORDINGS_URL`` (an fsspec URL or a folder: ``s3://bucket/stations``,
``file:///srv/calstation``). A run's files go to
``<store>/<station>/runs/<database identity>/<run id>/<file name>``, so that the runs of two
databases never share a place (copies made before, under ``<store>/<station>/runs/<run id>/``,
are kept where their artifacts say); each is copied and checked
(:func:`calstation.recordings.shared.upload`, which never replaces another object), then its
artifact's ``location`` is stored. The local copy is never touched: a failed upload leaves the
run as it was (the locations it had stay), and the next upload of the run sends only what is not
there yet.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from sqlalchemy import select

from calstation.errors import DatabaseError, FleetError
from calstation.recordings.shared import (
    SharedStorageError,
    StoreUnanswered,
    is_url,
    join,
    upload,
)
from calstation.storage.db import Artifact, Database, Run, RunStatus
from calstation.storage.report import find_run

STORE_ENV = "CALSTATION_RECORDINGS_URL"
"""The environment variable naming the shared store."""


PERSISTENT_SCHEMES = ("file", "s3", "s3a", "gs", "gcs", "az", "abfs", "abfss", "adl", "sftp",
                      "ssh", "hdfs", "webhdfs", "smb")
"""fsspec protocols whose copies outlive the process that wrote them (``memory://`` does not)."""


def recordings_store() -> str | None:
    """``$CALSTATION_RECORDINGS_URL``, or None when runs stay in their run folders only."""
    return os.environ.get(STORE_ENV) or None


def check_store(store: str) -> str:
    """``store`` if copies kept there outlive this process and can be found again from anywhere:
    a URL of :data:`PERSISTENT_SCHEMES`, or an absolute folder. :class:`FleetError` saying why
    not (``memory://`` vanishes with the process; ``s3:/bucket`` is a folder named ``s3:``)."""
    if is_url(store):
        scheme = store.split("://", 1)[0].lower()
        if scheme == "memory":
            raise FleetError(f"{store}: memory:// is this process's memory, and its copies "
                             "vanish when calstation ends; name a shared store (s3://, "
                             "file:///…, a folder)")
        if scheme not in PERSISTENT_SCHEMES:
            raise FleetError(f"{store}: {scheme}:// is not a store calstation keeps copies on; "
                             f"use one of {', '.join(s + '://' for s in PERSISTENT_SCHEMES)}")
        return store
    if re.match(r"^[A-Za-z][A-Za-z0-9+.-]*:", store):
        raise FleetError(f"{store!r} looks like a URL without its '//' (s3://bucket/…); as a "
                         "folder it would be named after the scheme")
    if not Path(store).expanduser().is_absolute():
        raise FleetError(f"{store!r}: a store folder must be an absolute path (a relative one "
                         "names another place from every folder calstation runs in)")
    return str(Path(store).expanduser())


@dataclass
class RunUpload:
    """What :func:`upload_run` did: files sent, already there (checked), and the errors of
    those that could not be sent (their local copies are kept)."""

    run_id: int
    sent: list[str] = field(default_factory=list)
    present: list[str] = field(default_factory=list)
    failed: list[str] = field(default_factory=list)
    unanswered: str | None = None
    """Why the upload stopped early: the store did not answer (the sentence naming it)."""

    @property
    def ok(self) -> bool:
        """Whether every file of the run has its shared copy now."""
        return not self.failed


def run_location(store: str, station: str, run_id: int, identity: str) -> str:
    """Where run ``run_id`` of ``station`` in the database ``identity`` goes in ``store``: its
    own place, whatever other databases upload to the same store."""
    return join(store, station, "runs", identity, str(run_id))


def legacy_run_location(store: str, station: str, run_id: int) -> str:
    """Where calstation put run ``run_id`` of ``station`` before run locations named their
    database: copies there are kept and still read (their artifacts record them)."""
    return join(store, station, "runs", str(run_id))


def upload_run(
    db: Database, run_id: int, store: str, say: Callable[[str], None] | None = None
) -> RunUpload:
    """Copy every file of run ``run_id`` that has no shared copy in ``store`` yet (see the
    module docstring); ``say`` is told of each file. ``store`` must keep its copies
    (:func:`check_store`). A store that does not answer ends the upload at the first file
    (:attr:`RunUpload.unanswered`): the others would wait as long."""
    store = check_store(store)
    tell = say or (lambda message: None)
    with db.session("reading the run's files", read_only=True) as s:
        run = find_run(s, run_id)
        if run is None:
            raise DatabaseError(f"no run with id {run_id} in the database")
        base = run_location(store, run.station.name, run_id, db.identity)
        there = (base + "/", legacy_run_location(store, run.station.name, run_id) + "/")
        files = [(a.id, Path(a.path), a.sha256) for a in run.artifacts
                 if not (a.location or "").startswith(there)]
    done = RunUpload(run_id)
    for art_id, path, sha256 in files:
        location = join(base, path.name)
        try:
            if not path.is_file():
                raise SharedStorageError(f"{path} is missing here: it cannot be uploaded")
            copied = upload(path, location, sha256)
        except SharedStorageError as exc:
            done.failed.append(str(exc))
            tell(f"not uploaded: {exc}")
            if isinstance(exc, StoreUnanswered):
                done.unanswered = str(exc)
                break
            continue
        with db.session("storing where a file was uploaded") as s:
            art = s.get(Artifact, art_id)
            assert art is not None
            art.location = location
        (done.sent if copied.sent or copied.resumed_from else done.present).append(location)
        tell(f"{path.name} → {location}" + (" (there already)" if not copied.sent else ""))
    return done


def runs_to_upload(db: Database, station: str | None = None, limit: int = 1000) -> list[int]:
    """Finished runs (of ``station``) with a file that has no shared copy yet, oldest first."""
    from calstation.storage.db import Station

    stmt = (select(Run.id).join(Artifact, Artifact.run_id == Run.id)
            .where(Artifact.location.is_(None), Run.status != RunStatus.RUNNING)
            .distinct().order_by(Run.id).limit(limit))
    if station is not None:
        stmt = stmt.join(Station, Run.station_id == Station.id).where(Station.name == station)
    with db.session("finding runs to upload", read_only=True) as s:
        return [int(i) for i in s.scalars(stmt)]
