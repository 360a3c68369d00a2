"""Storing a run as it goes: a step attempt's row when it starts, its outcome when it ends, and
the run's own start and end.

A step's end — its status and result, its recordings (``artifact``: path, size, sha256), its
calibration and cube check, and for the report step the run's verdict — is one change, committed
in one transaction; when the database fails it is journalled in the run folder instead
(:func:`calstation.storage.db.journal.store`), to be written by the next command. The read side
is :mod:`calstation.station.stored`.
"""

from __future__ import annotations

import math
import os
import socket
from typing import TYPE_CHECKING, Any

from sqlalchemy import select

from calstation.jsonvalue import JSONObject
from calstation.recordings.runfolder import file_sha256
from calstation.station.context import RunContext
from calstation.station.hardware import MotorStop
from calstation.station.outcome import CubeMeasurements, StepOutcome, plain
from calstation.station.stored import attempts
from calstation.storage.db import (
    Calibration,
    CubeCheckRecord,
    Database,
    Run,
    RunStatus,
    Step,
    StepStatus,
    journal,
    utcnow,
)
from calstation.storage.report import run_summary

if TYPE_CHECKING:
    from calstation.engine.result import CalibrationResult


def begin_step(db: Database, run_id: int, step: str) -> tuple[int, int]:
    """Store a ``running`` attempt of ``step``; (its row id, its attempt number)."""
    with db.session() as s:
        attempt = attempts(db, run_id, step) + 1
        row = Step(run_id=run_id, name=step, attempt=attempt, status=StepStatus.RUNNING)
        s.add(row)
        s.flush()
        return row.id, attempt


def end_step(
    ctx: RunContext,
    step_id: int,
    status: StepStatus,
    result: JSONObject,
    error: str | None,
    outcome: StepOutcome,
) -> None:
    """Commit the step's end, its artifacts and results in one transaction.

    Recordings cut short (``ctx.scans.partial``) are stored with the status ``partial``, those a
    step finished before it failed (``ctx.scans.finished``) as ``complete``. If the database
    fails, the change is journalled in the run folder and ResultJournalled raised
    (:func:`calstation.storage.db.journal.store`)."""
    partial, finished = ctx.scans.take()
    files = [(kind, path, path, "complete") for kind, path in outcome.artifacts]
    files += [(kind, final, tmp, "complete") for kind, tmp, final in outcome.staged]
    files += [(kind, path, path, "partial") for kind, path in partial if path.exists()]
    files += [(kind, path, path, "complete") for kind, path in finished
              if (kind, path) not in outcome.artifacts and path.exists()]
    artifacts = [
        {"kind": kind, "path": str(final), "size_bytes": source.stat().st_size,
         "sha256": file_sha256(source), "status": state}
        for kind, final, source, state in files
    ]
    calibration = cube = None
    if outcome.calibration is not None:
        stage, res = outcome.calibration
        calibration = journal.columns(calibration_row(ctx.run_id, step_id, stage, res))
    if outcome.cube is not None:
        cal_id, check = outcome.cube
        cube = journal.columns(cube_row(ctx.run_id, step_id, cal_id, check))
    change = journal.step_end(
        ctx.run_id, step_id, status, plain(result), error, artifacts=artifacts,
        calibration=calibration, cube=cube, run_status=outcome.run_status,
        accept_calibration=outcome.accept_calibration,
        staged=[(tmp, final) for _, tmp, final in outcome.staged],
    )
    journal.store(ctx.db, ctx.run_dir, change, f"the end of step {step_id}")


def mark_running(db: Database, run_id: int) -> None:
    """The run is executed by this process from now: attempts left ``running`` by an earlier
    process are ``interrupted``, and the run is ``running`` here (host, pid)."""
    with db.session() as s:
        for row in s.scalars(
            select(Step).where(Step.run_id == run_id, Step.status == StepStatus.RUNNING)
        ):
            row.status = StepStatus.INTERRUPTED
            row.error = "the process ended during this step"
            row.finished_at = row.finished_at or utcnow()
        run = s.get(Run, run_id)
        assert run is not None
        run.status = RunStatus.RUNNING
        run.finished_at = None
        run.error = None
        run.host = socket.gethostname()
        run.pid = os.getpid()


def end_run(
    ctx: RunContext, status: RunStatus, error: str | None
) -> dict[str, Any]:  # Any: storage's run mapping (calstation.storage.report.run_summary)
    """Store the run's end (journalled if the database fails: then DatabaseError is raised) and
    read back its summary (:func:`calstation.storage.report.run_summary`)."""
    journal.store(ctx.db, ctx.run_dir, journal.run_end(ctx.run_id, status, error),
                  f"the end of run {ctx.run_id}")
    with ctx.db.session("reading the run", read_only=True) as s:
        run = s.get(Run, ctx.run_id)
        assert run is not None
        return dict(run_summary(run))


def store_motor_stop(ctx: RunContext, record: MotorStop) -> None:
    """Store how the motor stopped (``run.motor_stop``); journalled (DatabaseError raised) when
    the database fails."""
    journal.store(ctx.db, ctx.run_dir, journal.motor_stop(ctx.run_id, dict(record)),
                  "how the motor stopped")


def calibration_row(
    run_id: int, step_id: int | None, stage: str, res: CalibrationResult
) -> Calibration:
    """The ``calibration`` row of a result ``res`` (a
    :class:`~calstation.engine.result.CalibrationResult`) of ``stage``, not accepted."""
    H = res.H.as_dict()
    sigma = {k: plain(float(v)) for k, v in res.sigma.items()}
    diagnostics = plain(dict(res.diagnostics))
    predicted = diagnostics.get("predicted_error")
    if res.timings:
        diagnostics["timings"] = plain(dict(res.timings))
    return Calibration(
        run_id=run_id,
        step_id=step_id,
        stage=stage,
        strategy=res.strategy,
        **H,
        **{f"sigma_{p}": sigma.get(p) for p in H},
        cost=plain(float(res.cost)),
        iterations=int(res.iterations),
        encoder_latency_s=plain(res.encoder_latency_s),
        sigma_encoder_latency_s=plain(res.sigma_encoder_latency_s),
        predicted_error_m=plain(predicted.get("max_m")) if isinstance(predicted, dict) else None,
        **{k: plain(v) for k, v in res.range_fields().items()},
        accepted=False,
        diagnostics=diagnostics,
    )


def cube_row(
    run_id: int, step_id: int, cal_id: int | None, c: CubeMeasurements
) -> CubeCheckRecord:
    """The ``cube_check`` row of a cube check ``c`` (as the cube scan's result holds it) made
    with calibration ``cal_id`` (None: the calibration stored with the same step)."""

    def number(key: str) -> float | None:
        # not measured: NULL (SQLite would store a NaN as NULL, PostgreSQL as NaN)
        v = c.get(key)
        return float(v) if isinstance(v, int | float) and math.isfinite(v) else None

    return CubeCheckRecord(
        run_id=run_id,
        step_id=step_id,
        calibration_id=cal_id,
        obb_edges=list(c.get("obb_edges") or []),
        obb_error=number("obb_error"),
        face_edges=list(c.get("face_edges") or []),
        edge_error=number("edge_error"),
        height_judged=bool(c.get("height_judged", True)),
        flatness_rms=number("flatness_rms"),
        perpendicularity_deg=number("perpendicularity_deg"),
        twist_deg=number("twist_deg"),
        twist_sigma_deg=number("twist_sigma_deg"),
        flatness_excess=number("flatness_excess"),
        range_noise=number("range_noise"),
        passed=bool(c.get("passed")),
        failures=[str(f) for f in c.get("failures") or []],
    )
