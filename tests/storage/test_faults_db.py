"""Fault injection, database: locks, lost writes, concurrent first runs, downgrades.

A lock is taken the way another process would take it (a second SQLite connection holding
``BEGIN IMMEDIATE``); a lost write is a driver error raised at the driver boundary
(``before_cursor_execute``) for the statements of one step. The station runs are the lean ones of
tests/support/station.py (simulated drivers, a stand-in strategy).
"""

from __future__ import annotations

import json
import multiprocessing
import os
import sqlite3
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import event, func, select, text

from calstation import hookimpl, plugins
from calstation.errors import DatabaseError
from calstation.recipes import load_recipe
from calstation.recordings.runfolder import file_sha256
from calstation.station.runs import resume_run, run_folder, start_run
from calstation.station.steps import STEPS
from calstation.storage.db import (
    Artifact,
    Calibration,
    CubeCheckRecord,
    Database,
    Run,
    Station,
    Step,
    get_or_create_station,
    journal as journal_mod,
    open_database,
)

pytest.importorskip("calstation_sim")
from tests.support.station import ScriptedOperator, StationTestPlugin, toy_recipe


class Holder:
    """Another connection's lock, held from :meth:`start` until :meth:`release`: the tests say
    when it ends (an event), never a number of seconds that a loaded machine may outlast."""

    def __init__(self, hold: Callable[[threading.Event, threading.Event], None]) -> None:
        self._held, self._release = threading.Event(), threading.Event()
        self._thread = threading.Thread(target=hold, args=(self._held, self._release),
                                        daemon=True)

    def start(self) -> Holder:
        self._thread.start()
        assert self._held.wait(600), "the lock was never taken"
        return self

    @property
    def holding(self) -> bool:
        return self._thread.is_alive() and not self._release.is_set()

    def release(self) -> None:
        self._release.set()

    def join(self) -> None:
        self.release()
        self._thread.join()


def hold_lock(path: Path) -> Holder:
    """Another process's write lock on the SQLite file ``path``, until released (returns once
    the lock is held)."""

    def hold(held: threading.Event, release: threading.Event) -> None:
        conn = sqlite3.connect(path, isolation_level=None, timeout=600)
        conn.execute("BEGIN IMMEDIATE")
        held.set()
        release.wait()
        conn.execute("COMMIT")
        conn.close()

    return Holder(hold).start()


# --- locks ---------------------------------------------------------------------------------
def test_a_lock_is_waited_for_and_said(tmp_path: Path) -> None:
    """The writer waits, says so, and writes once the lock is let go (here: when it has said
    so)."""
    said: list[str] = []
    holder: Holder | None = None

    def on_wait(message: str) -> None:
        said.append(message)
        assert holder is not None and holder.holding  # said while the lock was still held
        holder.release()

    db = Database(f"sqlite:///{tmp_path / 'w.db'}", lock_timeout=600, on_wait=on_wait)
    db.ensure_schema()
    holder = hold_lock(tmp_path / "w.db")
    station_id = get_or_create_station(db, "waited")
    holder.join()
    assert said and "waiting for the database" in said[0] and "up to 600 s" in said[0]
    with db.session() as s:
        assert s.get(Station, station_id) is not None
    db.dispose()


def test_a_lock_past_the_timeout_is_one_sentence_with_details_in_the_log(tmp_path: Path) -> None:
    db = Database(f"sqlite:///{tmp_path / 'l.db'}", lock_timeout=0.5, on_wait=lambda m: None)
    db.ensure_schema()
    db.log_path = tmp_path / "database.log"
    holder = hold_lock(tmp_path / "l.db")
    with pytest.raises(DatabaseError) as info:
        get_or_create_station(db, "x" * 50 + "-recipe-text-marker")
    holder.join()
    message = str(info.value)
    assert "stayed locked by another process for 0.5 s" in message
    assert f"details in {tmp_path / 'database.log'}" in message
    for leak in ("SELECT", "INSERT", "[SQL", "parameters", "recipe-text-marker", "sqlalche.me"):
        assert leak not in message, message
    log = (tmp_path / "database.log").read_text()
    assert "database is locked" in log and "[SQL: " in log
    db.dispose()


def test_a_runs_database_faults_go_to_its_folder_and_the_servers_pages_to_theirs(
        tmp_path: Path) -> None:
    """One database serves every page of a server while a run goes on: what fails in the run's
    thread is logged in the run's folder and told to its operator; what fails for a page stays
    in the server's log, not in the run's folder."""
    import threading

    db = Database(f"sqlite:///{tmp_path / 's.db'}", lock_timeout=0.5, on_wait=lambda m: None)
    db.log_path = tmp_path / "server" / "database.log"
    run_log = tmp_path / "runs" / "1" / "database.log"
    inside, done = threading.Event(), threading.Event()
    told: list[str] = []

    def run() -> None:
        with db.run_scope(run_log, told.append):
            db.error(RuntimeError("the run's write"), "storing the spin scan")
            inside.set()
            done.wait(30)

    thread = threading.Thread(target=run)
    thread.start()
    assert inside.wait(30)
    page = db.error(RuntimeError("a page's read"), "reading the runs")  # meanwhile, a page
    done.set()
    thread.join(30)
    assert f"details in {db.log_path}" in str(page)
    assert "a page's read" in db.log_path.read_text()
    assert "a page's read" not in run_log.read_text()
    assert "the run's write" in run_log.read_text()
    assert "the run's write" not in db.log_path.read_text()
    assert db.log_path == tmp_path / "server" / "database.log"  # nothing set on the object
    db.dispose()


def test_the_qa_commands_read_while_another_process_holds_the_write_lock(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """history, show and export read the last commit without waiting for a writer (WAL): a
    station that is writing never holds a QA engineer up, and is never held up by one."""
    from tests.support.clirun import run_cli

    monkeypatch.setenv("CALSTATION_HOME", str(tmp_path / "home"))
    path = tmp_path / "r.db"
    url = f"sqlite:///{path}"
    db = open_database(url)
    station_id = get_or_create_station(db, "reader")
    with db.session() as s:
        run = Run(station_id=station_id, recipe_name="sim", recipe_text="x: 1", recipe_sha256="ab",
                  operator="qa", data_dir=str(tmp_path), status="passed", unit_serial="S-17")
        s.add(run)
        s.flush()
        s.add(Calibration(run=run, stage="fine", strategy="periodicity", accepted=True,
                          tx=0.0123, ty=-0.004, tz=0.2, rx=0.0, ry=0.001, rz=0.5))
    db.dispose()
    monkeypatch.setenv("CALSTATION_DB_LOCK_TIMEOUT", "1")
    holder = hold_lock(path)
    with pytest.raises(DatabaseError, match="stayed locked"):  # the lock is really held
        get_or_create_station(Database(url), "writer")
    for argv in (["history", "--json"], ["show", "1", "--json"], ["export", "1", "-f", "json"]):
        code, out, err = run_cli([*argv, "--db", url], capsys)
        assert code == 0, err
        assert "S-17" in out or "0.0123" in out, (argv, out)
    assert holder.holding  # all of it while the lock was held
    holder.join()


def test_lock_timeout_is_configurable_and_checked(monkeypatch: pytest.MonkeyPatch,
                                                  tmp_path: Path) -> None:
    monkeypatch.setenv("CALSTATION_DB_LOCK_TIMEOUT", "7.5")
    assert Database(f"sqlite:///{tmp_path / 'c.db'}").lock_timeout == 7.5
    monkeypatch.setenv("CALSTATION_DB_LOCK_TIMEOUT", "forever")
    with pytest.raises(DatabaseError, match="CALSTATION_DB_LOCK_TIMEOUT='forever'"):
        Database(f"sqlite:///{tmp_path / 'c.db'}")


def _hold_pg_lock(url: str) -> Holder:
    """Another PostgreSQL session holding an exclusive lock on the station table, until
    released."""
    from sqlalchemy import create_engine

    def hold(held: threading.Event, release: threading.Event) -> None:
        engine = create_engine(url)
        with engine.begin() as conn:
            conn.exec_driver_sql("LOCK TABLE station IN ACCESS EXCLUSIVE MODE")
            held.set()
            release.wait()
        engine.dispose()

    return Holder(hold).start()


def test_a_postgresql_lock_is_waited_for_then_one_sentence(postgres_url: str) -> None:
    said: list[str] = []
    holder: Holder | None = None

    def on_wait(message: str) -> None:
        said.append(message)
        assert holder is not None
        holder.release()

    db = Database(postgres_url, lock_timeout=600, on_wait=on_wait)
    db.ensure_schema()
    holder = _hold_pg_lock(postgres_url)
    get_or_create_station(db, "pg-waited")
    holder.join()
    assert said and "waiting for the database" in said[0]
    db.dispose()
    short = Database(postgres_url, lock_timeout=0.5, on_wait=lambda m: None)
    holder = _hold_pg_lock(postgres_url)
    with pytest.raises(DatabaseError) as info:
        get_or_create_station(short, "pg-refused")
    holder.join()
    message = str(info.value)
    assert "stayed locked by another process for 0.5 s" in message
    assert "SELECT" not in message and "[SQL" not in message
    short.dispose()


# --- lost writes: journalled, written by the next command ----------------------------------
class FailingWrites:
    """Make the database refuse statements matching ``predicate`` while armed, as a lock that
    outlasts the wait would."""

    def __init__(self, db: Database, predicate: Callable[[str], bool]) -> None:
        self.armed = False
        self.predicate = predicate
        event.listen(db.engine, "before_cursor_execute", self._check)

    def _check(self, conn: Any, cursor: Any, statement: str, *args: Any) -> None:
        if self.armed and self.predicate(statement):
            raise sqlite3.OperationalError("database is locked")


class ArmAfter:
    """A plugin that arms a FailingWrites once ``step`` has finished."""

    __name__ = "arm-after"

    def __init__(self, failing: FailingWrites, step: str) -> None:
        self.failing, self.step = failing, step

    @hookimpl
    def calstation_step_finished(self, run: Any, step: str, status: str, result: Any) -> None:
        if step == self.step and status == "passed":
            self.failing.armed = True


def _lean_db(tmp_path: Path) -> Database:
    db = Database(f"sqlite:///{tmp_path / 'j.db'}", lock_timeout=0.5, on_wait=lambda m: None)
    db.ensure_schema()
    return db


def _run_losing_step_updates_after(
    tmp_path: Path, step: str, ui: ScriptedOperator | None = None
) -> tuple[Database, FailingWrites, int]:
    """A lean run whose step updates fail from ``step`` on: (its database, the failing writes
    to disarm, the run id); the run ended ``interrupted``."""
    db = _lean_db(tmp_path)
    failing = FailingWrites(db, lambda sql: sql.startswith("UPDATE step"))
    plugins.get_plugin_manager().register(ArmAfter(failing, step))
    run_id, status = start_run(load_recipe(toy_recipe(tmp_path)), db,
                               ui or ScriptedOperator(), operator="ann", data_dir=tmp_path)
    assert status == "interrupted"
    return db, failing, run_id


def _step_rows(db: Database, run_id: int) -> list[tuple[str, str]]:
    with db.session() as s:
        return [(r.name, r.status) for r in
                s.scalars(select(Step).where(Step.run_id == run_id).order_by(Step.id))]


def test_a_lost_step_end_is_journalled_and_written_by_the_next_command(
    tmp_path: Path, station_plugin: StationTestPlugin
) -> None:
    ui = ScriptedOperator()
    db, failing, run_id = _run_losing_step_updates_after(tmp_path, "place_spin_target", ui)
    run_dir = run_folder(db, run_id)
    entries = journal_mod.read(run_dir / "journal.jsonl")
    assert [e["op"] for e in entries] == ["step_end", "run_end"]
    assert entries[0]["status"] == "passed"  # the spin scan's end, with its recording
    assert entries[0]["artifacts"][0]["kind"] == "spin"
    assert any("is kept in" in m and "journal.jsonl" in m for m in ui.messages)
    with db.session() as s:  # the database does not hold it yet
        assert s.get(Run, run_id).status == "running"  # type: ignore[union-attr]
    failing.armed = False
    # the motor stop was stored directly (another statement), the run shows how
    with db.session() as s:
        assert s.get(Run, run_id).motor_stop["ok"]  # type: ignore[union-attr,index]
    # the next command writes the journal
    again = open_database(db.url)
    with again.session() as s:
        run = s.get(Run, run_id)
        assert run is not None and run.status == "interrupted"
        spin = s.scalars(select(Artifact).where(Artifact.run_id == run_id,
                                                Artifact.kind == "spin")).one()
        assert file_sha256(Path(spin.path)) == spin.sha256
    assert ("spin_scan", "passed") in _step_rows(again, run_id)
    assert not (run_dir / "journal.jsonl").exists() and (run_dir / "journal.applied.jsonl").exists()
    # and the run resumes after the stored spin scan, to its end
    status = resume_run(run_id, again, ScriptedOperator())
    assert status in ("passed", "failed")
    rows = _step_rows(again, run_id)
    assert [n for n, st in rows if st == "passed"][-4:] == ["fine_tune", "place_qa_cube",
                                                             "cube_scan", "report"]
    assert sum(1 for n, st in rows if n == "spin_scan") == 1  # the scan was not repeated
    again.dispose()
    db.dispose()


def test_a_lost_calibration_is_journalled_with_its_step_and_written_later(
    tmp_path: Path, station_plugin: StationTestPlugin
) -> None:
    db, failing, run_id = _run_losing_step_updates_after(tmp_path, "spin_scan")
    entries = journal_mod.read(run_folder(db, run_id) / "journal.jsonl")
    fine = entries[0]["calibration"]
    assert entries[0]["status"] == "passed" and fine["stage"] == "fine"
    with db.session() as s:
        assert s.scalars(select(Calibration).where(Calibration.stage == "fine")).first() is None
    failing.armed = False
    again = open_database(db.url)
    with again.session() as s:
        stored = s.scalars(select(Calibration).where(Calibration.run_id == run_id,
                                                     Calibration.stage == "fine")).one()
        assert stored.params() == {k: fine[k] for k in ("tx", "ty", "tz", "rx", "ry", "rz")}
        assert stored.diagnostics is not None and stored.diagnostics["note"] == "toy"
    assert ("fine_tune", "passed") in _step_rows(again, run_id)
    # replaying the same journal again changes nothing
    applied = run_folder(db, run_id) / "journal.applied.jsonl"
    with again.session() as s:
        for entry in journal_mod.read(applied):
            journal_mod.APPLY[entry["op"]](s, entry)
    with again.session() as s:
        assert len(s.scalars(select(Calibration).where(Calibration.run_id == run_id,
                                                       Calibration.stage == "fine")).all()) == 1
    again.dispose()
    db.dispose()


def test_report_json_never_claims_a_verdict_the_database_does_not_hold(
    tmp_path: Path, station_plugin: StationTestPlugin
) -> None:
    db, failing, run_id = _run_losing_step_updates_after(tmp_path, "cube_scan")
    run_dir = run_folder(db, run_id)
    assert not (run_dir / "report.json").exists()  # staged, not in place
    assert [p for p in run_dir.iterdir() if p.name.startswith(".report.json.")]  # staged
    failing.armed = False
    again = open_database(db.url)
    report = json.loads((run_dir / "report.json").read_text())
    with again.session() as s:
        run = s.get(Run, run_id)
        assert run is not None
        assert report["status"] == run.status and run.status in ("passed", "failed")
        accepted = [c for c in run.calibrations if c.accepted]
        assert len(accepted) == (1 if run.status == "passed" else 0)
        kinds = {a.kind for a in run.artifacts}
    assert {"static", "spin", "cube", "report", "calibration"} <= kinds
    calibration = (run_dir / "calibration.yaml").read_text()
    assert f"status: {report['status']}" in calibration
    assert {n for n, st in _step_rows(again, run_id) if st == "passed"} == set(STEPS)
    again.dispose()
    db.dispose()


def test_a_run_left_running_by_a_dead_process_shows_interrupted(tmp_path: Path) -> None:
    db = open_database(f"sqlite:///{tmp_path / 'd.db'}")
    station_id = get_or_create_station(db, "st")
    import subprocess
    import sys

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)
    import socket

    with db.session() as s:
        run = Run(station_id=station_id, recipe_name="r", recipe_text="", recipe_sha256="0" * 64,
                  operator="ann", data_dir=str(tmp_path / "gone"), status="running",
                  host=socket.gethostname(), pid=int(dead.stdout))
        s.add(run)
        s.flush()
        s.add(Step(run_id=run.id, name="spin_scan", status="running"))
        run_id = run.id
    again = open_database(db.url)
    with again.session() as s:
        run = s.get(Run, run_id)
        assert run is not None and run.status == "interrupted"
        assert run.steps[0].status == "interrupted"
    again.dispose()
    db.dispose()


# --- concurrent first runs -----------------------------------------------------------------
def _open_and_register(url: str, name: str, barrier: Any, out: Any) -> None:
    try:
        barrier.wait(30)
        db = open_database(url)
        out.put(("ok", get_or_create_station(db, name)))
        db.dispose()
    except Exception as exc:  # reported to the test
        out.put(("error", f"{type(exc).__name__}: {exc}"))


def _race(url: str, processes: int = 3) -> list[tuple[str, Any]]:
    ctx = multiprocessing.get_context("fork")  # each child opens its own engine
    barrier = ctx.Barrier(processes)
    out = ctx.Queue()
    procs = [ctx.Process(target=_open_and_register, args=(url, "sim-01", barrier, out))
             for _ in range(processes)]
    for p in procs:
        p.start()
    results = [out.get(timeout=120) for _ in procs]
    for p in procs:
        p.join(60)
    return results


def test_concurrent_first_opens_of_a_fresh_sqlite_database_all_succeed(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'fresh.db'}"
    results = _race(url)
    assert all(r[0] == "ok" for r in results), results
    assert len({r[1] for r in results}) == 1  # one station row, shared
    db = Database(url)
    with db.session() as s:
        assert s.scalar(select(func.count()).select_from(Station)) == 1
    db.dispose()


def test_concurrent_first_opens_of_a_fresh_postgresql_database_all_succeed(
    postgres_url: str,
) -> None:
    db = Database(postgres_url)
    with db.engine.begin() as conn:  # a fresh database: nothing from other tests
        conn.execute(text("DROP SCHEMA public CASCADE"))
        conn.execute(text("CREATE SCHEMA public"))
    db.dispose()
    results = _race(postgres_url)
    assert all(r[0] == "ok" for r in results), results
    assert len({r[1] for r in results}) == 1


# --- downgrades keep the rows --------------------------------------------------------------
COUNTED = (Station, Run, Step, Calibration, CubeCheckRecord, Artifact)


def _populate(db: Database) -> None:
    station_id = get_or_create_station(db, "pop")
    with db.session() as s:
        for r in range(3):
            run = Run(station_id=station_id, recipe_name="r", recipe_text="name: r\n",
                      recipe_sha256="0" * 64, operator="ann", data_dir=f"/tmp/run{r}",
                      status="passed")
            s.add(run)
            s.flush()
            for i, name in enumerate(STEPS):
                step = Step(run_id=run.id, name=name, status="passed", result={"i": i})
                s.add(step)
                s.flush()
                if name == "static_scan":
                    s.add(Artifact(run_id=run.id, step_id=step.id, kind="static",
                                   path=f"/tmp/run{r}/static.mcap", size_bytes=10,
                                   sha256="1" * 64))
            cal = Calibration(run_id=run.id, stage="fine", strategy="periodicity", tx=0.0,
                              ty=1.0, tz=0.0, rx=0.0, ry=0.0, rz=-0.7, accepted=True)
            s.add(cal)
            s.flush()
            s.add(CubeCheckRecord(run_id=run.id, calibration_id=cal.id, obb_edges=[0.1] * 3,
                                  obb_error=0.001, face_edges=[0.1] * 3, edge_error=0.0005,
                                  flatness_rms=0.0002, perpendicularity_deg=0.1, passed=True,
                                  failures=[]))


def _counts(db: Database) -> dict[str, int]:
    with db.engine.connect() as conn:
        return {m.__tablename__: int(conn.execute(
            text(f"SELECT count(*) FROM {m.__tablename__}")).scalar() or 0) for m in COUNTED}


def _downgrade_and_upgrade_keep_rows(db: Database) -> None:
    _populate(db)
    before = _counts(db)
    assert before["step"] == 27 and before["artifact"] == 3
    for revision in ("0002", "0001"):
        db.downgrade(revision)
        assert _counts(db) == before, revision
    db.upgrade()
    assert _counts(db) == before
    with db.session() as s:  # the new columns are back, with their defaults
        assert {a.status for a in s.scalars(select(Artifact))} == {"complete"}
    with pytest.raises(DatabaseError, match=r"holds 3 run\(s\); downgrading below revision 0001 "
                                            "would drop every table"):
        db.downgrade("base")
    assert _counts(db) == before


def test_downgrade_and_upgrade_keep_every_row_sqlite(tmp_path: Path) -> None:
    db = open_database(f"sqlite:///{tmp_path / 'down.db'}")
    _downgrade_and_upgrade_keep_rows(db)
    db.dispose()


def test_downgrade_and_upgrade_keep_every_row_postgresql(postgres_url: str) -> None:
    db = Database(postgres_url)
    with db.engine.begin() as conn:
        conn.execute(text("DROP SCHEMA public CASCADE"))
        conn.execute(text("CREATE SCHEMA public"))
    db.ensure_schema()
    _downgrade_and_upgrade_keep_rows(db)
    db.dispose()


def test_cli_downgrade_of_a_populated_database(tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    from calstation.cli import main

    url = f"sqlite:///{tmp_path / 'cli.db'}"
    db = open_database(url)
    _populate(db)
    before = _counts(db)
    with pytest.raises(SystemExit) as info:
        main(["db", "downgrade", "0001", "--db", url])
    assert info.value.code in (0, None)
    assert _counts(db) == before
    with pytest.raises(SystemExit) as info:
        main(["db", "downgrade", "base", "--db", url])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert "would drop every table" in err and "Traceback" not in err
    db.dispose()


def test_a_journalled_result_is_on_the_disk_before_the_run_goes_on(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The journal is what survives a lost database and then a power cut: each entry is
    flushed to the disk (fsync of the journal, with the entry in it) before append returns."""
    synced: list[tuple[str, int]] = []
    real = os.fsync

    def fsync(fd: int) -> None:
        synced.append((os.readlink(f"/proc/self/fd/{fd}"), os.fstat(fd).st_size))
        real(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    entry = journal_mod.run_end(7, "interrupted", "the database went away")
    path = journal_mod.append(tmp_path / "runs" / "7", entry)
    size = path.stat().st_size
    assert (str(path), size) in synced
    assert journal_mod.read(path) == [entry]
