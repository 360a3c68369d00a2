"""Results that could not be written: kept in the run folder, written by the next command.

When a step's end (its status, result, recordings, calibration, cube check) or the run's end
cannot be committed — the database stayed locked past its timeout, or went away — the station
appends the same change, as one JSON line, to ``journal.jsonl`` in the run folder and stops the
run as ``interrupted``. The next calstation command that opens the database (``resume``,
``history``, ``show``, ``run``...) calls :func:`recover`, which applies every journalled change
in one transaction, renames the journal to ``journal.applied.jsonl``, and marks runs whose process
has ended without finishing them ``interrupted`` (never ``running`` forever).

Each change is applied by one function, used both for the direct commit and for the replay, so
the two cannot differ; applying a change twice is harmless.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import socket
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from sqlalchemy import inspect as sa_inspect, select
from sqlalchemy.orm import Session

from calstation.atomic import commit
from calstation.errors import DatabaseError, ResultJournalled
from calstation.recordings.runfolder import SCAN_RECORDINGS, file_sha256
from calstation.storage.db.database import Database
from calstation.storage.db.models import (
    Artifact,
    Base,
    Calibration,
    CubeCheckRecord,
    Run,
    RunStatus,
    Step,
    StepStatus,
    utcnow,
)

JOURNAL = "journal.jsonl"
"""The journal's file name in the run folder."""
APPLIED = "journal.applied.jsonl"
"""Where applied journal entries are kept (appended), for the record."""

Payload = dict[str, Any]  # Any: an entry read back from JSON, applied field by field


def _iso(t: dt.datetime | None = None) -> str:
    return (t or utcnow()).isoformat()


def _time(text: str | None) -> dt.datetime | None:
    return dt.datetime.fromisoformat(text) if text else None


def columns(row: Base, skip: tuple[str, ...] = ("id", "created_at")) -> dict[str, object]:
    """The column values of an ORM row not yet stored (for a journal entry)."""
    return {
        attr.key: getattr(row, attr.key)
        for attr in sa_inspect(type(row)).column_attrs
        if attr.key not in skip and getattr(row, attr.key) is not None
    }


# --- the changes ---------------------------------------------------------------------------
def step_end(
    run_id: int,
    step_id: int,
    status: str,
    result: Mapping[str, object],
    error: str | None,
    *,
    artifacts: Sequence[Mapping[str, object]] | None = None,
    calibration: Mapping[str, object] | None = None,
    cube: Mapping[str, object] | None = None,
    run_status: str | None = None,
    accept_calibration: int | None = None,
    staged: list[tuple[Path, Path]] | None = None,
) -> Payload:
    """The end of one step attempt: status, result, artifacts (``kind``, ``path``,
    ``size_bytes``, ``sha256``, ``status``), a calibration and a cube-check row (column values),
    the run's verdict (the report step) with the calibration it accepts, and files written under
    a temporary name to move into place once stored (``staged``: (temporary, final))."""
    return {
        "op": "step_end",
        "run_id": run_id,
        "step_id": step_id,
        "status": status,
        "finished_at": _iso(),
        "result": result,
        "error": error,
        "artifacts": artifacts or [],
        "calibration": calibration,
        "cube": cube,
        "run_status": run_status,
        "accept_calibration": accept_calibration,
        "staged": [[str(a), str(b)] for a, b in staged or []],
    }


def run_end(run_id: int, status: str, error: str | None) -> Payload:
    """The end of a run: its final status and error."""
    return {"op": "run_end", "run_id": run_id, "status": status, "error": error,
            "finished_at": _iso()}


def motor_stop(run_id: int, record: Mapping[str, object]) -> Payload:
    """How the turntable was stopped when the run's drivers closed."""
    return {"op": "motor_stop", "run_id": run_id, "motor_stop": record}


def _apply_step_end(s: Session, p: Payload) -> None:
    row = s.get(Step, p["step_id"])
    if row is None:
        raise DatabaseError(f"step {p['step_id']} of run {p['run_id']} is not in the database")
    row.status = p["status"]
    row.finished_at = _time(p["finished_at"])
    row.result = p["result"]
    row.error = p["error"]
    for a in p["artifacts"]:
        known = s.scalars(select(Artifact.id).where(
            Artifact.run_id == p["run_id"], Artifact.step_id == p["step_id"],
            Artifact.kind == a["kind"], Artifact.path == a["path"])).first()
        if known is None:
            s.add(Artifact(run_id=p["run_id"], step_id=p["step_id"], **a))
    cal = p.get("calibration")
    cal_id = None
    if cal is not None:
        cal_id = s.scalars(select(Calibration.id).where(
            Calibration.step_id == p["step_id"], Calibration.stage == cal["stage"])).first()
        if cal_id is None:
            cal_row = Calibration(**cal)
            s.add(cal_row)
            s.flush()
            cal_id = cal_row.id
    cube = p.get("cube")
    if cube is not None and s.scalars(select(CubeCheckRecord.id).where(
            CubeCheckRecord.step_id == p["step_id"])).first() is None:
        if cube.get("calibration_id") is None:
            cube = {**cube, "calibration_id": cal_id}  # the check of the calibration stored here
        s.add(CubeCheckRecord(**cube))
    if p.get("run_status"):
        run = s.get(Run, p["run_id"])
        if run is not None:
            run.status = p["run_status"]
            for c in run.calibrations:
                c.accepted = c.id == p.get("accept_calibration")


def _apply_run_end(s: Session, p: Payload) -> None:
    run = s.get(Run, p["run_id"])
    if run is None:
        raise DatabaseError(f"run {p['run_id']} is not in the database")
    reported = any(st.name == "report" and st.status == StepStatus.PASSED for st in run.steps)
    if not (p["status"] == RunStatus.INTERRUPTED and reported):
        # (a run whose report is stored has finished with its verdict, even if the process
        # could not store its end)
        run.status = p["status"]
        run.error = p["error"]
    run.finished_at = _time(p["finished_at"])
    for row in s.scalars(select(Step).where(Step.run_id == run.id,
                                            Step.status == StepStatus.RUNNING)):
        row.status = (StepStatus.INTERRUPTED if p["status"] == RunStatus.INTERRUPTED
                      else p["status"])
        row.error = row.error or p["error"]
        row.finished_at = row.finished_at or run.finished_at


def _apply_motor_stop(s: Session, p: Payload) -> None:
    run = s.get(Run, p["run_id"])
    if run is not None:
        run.motor_stop = p["motor_stop"]


APPLY: dict[str, Callable[[Session, Payload], None]] = {
    "step_end": _apply_step_end,
    "run_end": _apply_run_end,
    "motor_stop": _apply_motor_stop,
}


def _move_staged(p: Payload) -> None:
    for tmp, final in p.get("staged") or []:
        if Path(tmp).exists():
            commit(tmp, final, Path(final).name)


# --- writing, or journalling ---------------------------------------------------------------
def append(run_dir: Path, payload: Payload) -> Path:
    """Append ``payload`` to the run folder's journal (flushed to disk); the journal's path."""
    path = run_dir / JOURNAL
    run_dir.mkdir(parents=True, exist_ok=True)
    with path.open("a", encoding="utf-8") as f:
        f.write(json.dumps(payload) + "\n")
        f.flush()
        os.fsync(f.fileno())
    return path


def store(db: Database, run_dir: Path, payload: Payload, what: str) -> None:
    """Commit ``payload``; if the database fails, journal it and raise
    :class:`~calstation.errors.ResultJournalled` (one sentence: why, and where it is kept).
    Staged files are moved into place only once the change is stored."""
    try:
        with db.session(f"storing {what}") as s:
            APPLY[payload["op"]](s, payload)
    except DatabaseError as exc:
        try:
            path = append(run_dir, payload)
        except OSError as os_exc:
            raise DatabaseError(
                f"{exc}; and {what} could not be journalled either: {os_exc}"
            ) from exc
        raise ResultJournalled(
            f"{exc}. {what[0].upper()}{what[1:]} is kept in {path}; the next calstation command "
            "that opens the database (resume, history, show) writes it"
        ) from exc
    _move_staged(payload)


def read(path: Path) -> list[Payload]:
    """The entries of a journal (a torn last line, from a crash while writing, is skipped)."""
    entries = []
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            entry = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(entry, dict) and entry.get("op") in APPLY:
            entries.append(entry)
    return entries


# --- recovery ------------------------------------------------------------------------------
def _owner_alive(host: str | None, pid: int | None) -> bool | None:
    """Whether the process that executes a run is alive: None when it cannot be told."""
    if pid is None or host != socket.gethostname():
        return None
    return pid == os.getpid() or process_alive(pid)


def process_alive(pid: int) -> bool:
    """Whether process ``pid`` exists on this host (one we may not signal counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _register_partial_recordings(s: Session, run_id: int, run_dir: Path) -> list[str]:
    """Store the recordings of scans a dead process left running as ``partial`` artifacts."""
    kept = []
    for step in s.scalars(select(Step).where(Step.run_id == run_id,
                                             Step.status == StepStatus.RUNNING)):
        stems = SCAN_RECORDINGS.get(step.name, ())
        paths = [(kind, run_dir / f"{kind}.mcap") for kind in stems]
        present = [(kind, path) for kind, path in paths if path.is_file()]
        for i, (kind, path) in enumerate(present):
            if s.scalars(select(Artifact.id).where(Artifact.path == str(path))).first() is not None:
                continue
            # a recording followed by the step's next one was finished before that began
            status = "complete" if i < len(present) - 1 else "partial"
            s.add(Artifact(run_id=run_id, step_id=step.id, kind=kind, path=str(path),
                           size_bytes=path.stat().st_size, sha256=file_sha256(path),
                           status=status))
            kept.append(path.name)
    return kept


def recover(db: Database) -> list[str]:
    """Write journalled results and mark abandoned runs ``interrupted``; what was done, in words.

    A run's journal is applied once it is closed (it ends with the run's end) or once the process
    that wrote it has ended; a run still ``running`` whose process (on this host) has ended is
    marked ``interrupted``, with its running steps.
    """
    notes: list[str] = []
    with db.session("reading the runs", read_only=True) as s:
        rows = s.execute(
            select(Run.id, Run.data_dir, Run.host, Run.pid).where(Run.status == RunStatus.RUNNING)
        ).all()
    for run_id, data_dir, host, pid in rows:
        alive = _owner_alive(host, pid)
        journal = Path(data_dir) / JOURNAL if data_dir else None
        entries = read(journal) if journal is not None and journal.is_file() else []
        closed = any(e["op"] == "run_end" for e in entries)
        if entries and journal is not None and (closed or alive is False):
            with db.session(f"writing the journal of run {run_id}") as s:
                for entry in entries:
                    APPLY[entry["op"]](s, entry)
            for entry in entries:
                _move_staged(entry)
            with (journal.parent / APPLIED).open("a", encoding="utf-8") as f:
                f.write(journal.read_text(encoding="utf-8"))
            journal.unlink()
            notes.append(f"run {run_id}: wrote {len(entries)} result(s) kept in {journal} while "
                         "the database was unavailable")
        if not closed and alive is False:
            with db.session(f"marking run {run_id} interrupted") as s:
                kept = _register_partial_recordings(s, run_id, Path(data_dir))
                _apply_run_end(s, run_end(
                    run_id, RunStatus.INTERRUPTED,
                    f"process {pid} ended before the run finished"))
            if kept:
                notes.append(f"run {run_id}: kept {', '.join(kept)} as partial recording(s)")
            notes.append(f"run {run_id} was left running by process {pid}, which has ended: "
                         f"marked interrupted (continue it with `calstation resume {run_id}`)")
    return notes
