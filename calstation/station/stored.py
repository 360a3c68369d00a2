"""What a run has stored so far, read back: its steps and attempts, its calibrations, its
recordings (checked against their stored sha256) and its cube verdict.

The read side of a run's database rows, for the station and its steps; the write side is
:mod:`calstation.station.persist`.
"""

from __future__ import annotations

from contextlib import suppress
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sqlalchemy import select

from calstation.errors import CalstationError, StationError
from calstation.plugins.hookspecs import RunBrief, run_brief_payload
from calstation.recordings.shared import SharedStorageError, StoredFile, local_copy
from calstation.storage.db import (
    Artifact,
    Calibration,
    CubeCheckRecord,
    Database,
    Run,
    RunStatus,
    Step,
    StepStatus,
)
from calstation.storage.report import run_brief

if TYPE_CHECKING:
    from calstation.engine.frames import Extrinsics


def stored_file(art: Artifact) -> StoredFile:
    """An artifact as :func:`calstation.recordings.shared.local_copy` takes it."""
    return StoredFile(art.path, art.sha256, art.size_bytes, art.location)


def checked_recording(
    art: Artifact | StoredFile | None, run_id: int, kind: str, error: type[CalstationError]
) -> Path:
    """The local path of a stored ``kind`` recording of run ``run_id`` after checking that its
    bytes are the stored ones (sha256): the run folder's file, else its shared copy
    (``artifact.location``) fetched and checked; ``error`` names what is wrong."""
    if art is None:
        raise error(f"run {run_id} has no {kind} recording stored")
    stored = art if isinstance(art, StoredFile) else stored_file(art)
    try:
        return local_copy(stored)
    except SharedStorageError as exc:
        raise error(f"the {kind} recording of run {run_id}: {exc}") from None


def artifact_path(db: Database, run_id: int, kind: str) -> Path:
    """The newest complete ``kind`` recording of run ``run_id``, checked
    (:func:`checked_recording`); :class:`StationError` when missing or changed."""
    with db.session() as s:
        art = s.scalars(
            select(Artifact)
            .where(Artifact.run_id == run_id, Artifact.kind == kind,
                   Artifact.status == "complete")
            .order_by(Artifact.id.desc())
        ).first()
    return checked_recording(art, run_id, kind, StationError)


def stored_calibration(db: Database, run_id: int, stage: str) -> Calibration:
    """The newest ``stage`` calibration of run ``run_id`` (``initial``, ``fine``);
    :class:`StationError` when there is none."""
    with db.session() as s:
        cal = s.scalars(
            select(Calibration)
            .where(Calibration.run_id == run_id, Calibration.stage == stage)
            .order_by(Calibration.id.desc())
        ).first()
    if cal is None:
        raise StationError(f"run {run_id} has no {stage} calibration stored")
    return cal


def latest_calibration(db: Database, run_id: int) -> tuple[Extrinsics | None, str]:
    """The run's newest calibration (fine before initial) and its stage, for a recording's
    static transform and cloud; (None, "") before the first one."""
    from calstation.engine.frames import Extrinsics

    for stage in ("fine", "initial"):
        with suppress(StationError):
            cal = stored_calibration(db, run_id, stage)
            return Extrinsics.from_dict(cal.params()), stage
    return None, ""


def attempts(db: Database, run_id: int, step: str) -> int:
    """How many attempts of ``step`` run ``run_id`` has stored, whatever their status."""
    with db.session() as s:
        return len(
            s.scalars(select(Step.id).where(Step.run_id == run_id, Step.name == step)).all()
        )


def passed_result(
    db: Database, run_id: int, step: str
) -> dict[str, Any]:  # Any: a stored step's JSON column, read key by key
    """The stored result of run ``run_id``'s newest passed ``step`` ({} when none passed)."""
    with db.session() as s:
        result = s.scalars(
            select(Step.result)
            .where(Step.run_id == run_id, Step.name == step, Step.status == StepStatus.PASSED)
            .order_by(Step.id.desc())
        ).first()
    return dict(result or {})


def passed_steps(db: Database, run_id: int) -> set[str]:
    """The steps of run ``run_id`` with a passed attempt."""
    with db.session() as s:
        return set(
            s.scalars(select(Step.name).where(Step.run_id == run_id,
                                              Step.status == StepStatus.PASSED))
        )


def cube_verdict(db: Database, run_id: int) -> RunStatus:
    """``passed`` when the run's newest cube check passed, else ``failed`` (none is a fail)."""
    with db.session() as s:
        check = s.scalars(
            select(CubeCheckRecord)
            .where(CubeCheckRecord.run_id == run_id)
            .order_by(CubeCheckRecord.id.desc())
        ).first()
    return RunStatus.PASSED if check is not None and check.passed else RunStatus.FAILED


def cube_failure(db: Database, run_id: int) -> str | None:
    """Why the run's newest cube check failed; None when it passed or there is none."""
    with db.session() as s:
        check = s.scalars(
            select(CubeCheckRecord)
            .where(CubeCheckRecord.run_id == run_id)
            .order_by(CubeCheckRecord.id.desc())
        ).first()
        if check is None or check.passed:
            return None
        return "cube check failed: " + "; ".join(str(f) for f in check.failures)


def brief(db: Database, run_id: int) -> RunBrief:
    """The run as the observer hooks see it (:func:`calstation.storage.report.run_brief`)."""
    with db.session() as s:
        run = s.get(Run, run_id)
        assert run is not None
        return run_brief_payload(run_brief(run))
