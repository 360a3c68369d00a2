"""The station state machine on the simulated station, with a scripted operator.

The drivers are the real simulated ones (wrapped to observe motor commands or to wire the encoder
backwards); the fine-tuning strategy is a small stand-in so these tests exercise the station, not
the optimiser (tests/system/test_e2e.py runs the real engine end to end).
"""

from __future__ import annotations

import json
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml

from calstation import plugins
from calstation.errors import RecipeError, StationError
from calstation.recipes import load_recipe
from calstation.recordings.runfolder import file_sha256
from calstation.station.machine import next_in_order
from calstation.station.runs import resume_run, start_run
from calstation.station.steps import REGISTRY, STEPS
from calstation.storage.db import Artifact, Calibration, Database, Run, Step, open_database
from tests.support.station import (
    ScriptedOperator,
    StationTestPlugin,
    UnattendedOperator,
    toy_recipe,
)

calstation_sim = pytest.importorskip("calstation_sim")
from calstation_sim import plugin as sim_plugin  # noqa: E402

RECIPES = Path(__file__).resolve().parents[2] / "recipes"


def _steps(db: Database, run_id: int) -> list[tuple[str, int, str]]:
    with db.session() as s:
        return [(r.name, r.attempt, r.status)
                for r in s.query(Step).filter_by(run_id=run_id).order_by(Step.id)]


def _stop_at(step_name: str) -> Callable[[str], bool]:
    """Operator who aborts when asked to place ``step_name``'s fixture."""
    return lambda fixture: fixture != step_name


def test_run_until_abort_commits_each_step_and_stops_the_motor(
    tmp_path: Path, db: Database, station_plugin: StationTestPlugin
) -> None:
    ui = ScriptedOperator(place=_stop_at("qa_cube"))
    log_path, on_wait = db.log_path, db.on_wait
    run_id, status = start_run(load_recipe(toy_recipe(tmp_path)), db, ui, operator="ann",
                               data_dir=tmp_path / "data")
    assert status == "aborted"
    # the run's database log and waits were its own, not set on the shared database object
    assert db.log_path == log_path and db.on_wait is on_wait
    assert _steps(db, run_id) == [
        ("preflight", 1, "passed"), ("place_static_target", 1, "passed"),
        ("static_scan", 1, "passed"), ("place_spin_target", 1, "passed"),
        ("spin_scan", 1, "passed"), ("fine_tune", 1, "passed"), ("place_qa_cube", 1, "aborted"),
    ]
    assert ui.placed == ["static_target", "spin_target", "qa_cube"]
    # the spin scan was prepared as it arrived: the fine-tuning says how long after the scan
    # its result was ready
    with db.session() as s:
        fine = s.query(Step).filter_by(run_id=run_id, name="fine_tune").one().result
    assert fine is not None and 0 < fine["after_scan_s"] < 120
    assert any("after the scan ended" in line for line in ui.messages)
    # abort: the motor got an emergency stop and a stop, whatever it was doing
    assert station_plugin.motor_calls[-2:] == ["emergency_stop", "stop"]
    run_dir = tmp_path / "data" / "runs" / db.identity / str(run_id)
    with db.session() as s:
        run = s.get(Run, run_id)
        assert run is not None and run.status == "aborted" and run.operator == "ann"
        assert run.data_dir == str(run_dir.resolve())
        arts = {a.kind: a for a in s.query(Artifact).filter_by(run_id=run_id)}
        cals = {c.stage: c for c in s.query(Calibration).filter_by(run_id=run_id)}
    assert set(arts) == {"static", "spin"}
    for kind, art in arts.items():
        path = Path(art.path)
        assert path == (run_dir / f"{kind}.mcap").resolve()
        assert art.size_bytes == path.stat().st_size and art.sha256 == file_sha256(path)
    assert cals["fine"].tx == pytest.approx(cals["initial"].tx + 1e-4)
    assert cals["fine"].strategy == "toy" and not cals["fine"].accepted
    assert ("spin_scan", "passed") in station_plugin.events
    assert station_plugin.events[-1] == ("run", "aborted")
    # the simulator's ground truth went into the recordings
    from calstation.recordings.reader import read_recording

    rec = read_recording(arts["static"].path)
    assert rec.truth is not None and rec.metadata["run"]["id"] == run_id
    # a station's recordings are on its drivers' clock, the calibration's transform included
    from tests.support.one_clock import check_one_clock

    for art in arts.values():
        check_one_clock(Path(art.path))
    assert "static scan" in ui.progress_titles and "spin scan" in ui.progress_titles


def test_preflight_catches_a_reversed_encoder(
    tmp_path: Path, db: Database, station_plugin: StationTestPlugin
) -> None:
    ui = ScriptedOperator()
    run_id, status = start_run(load_recipe(toy_recipe(tmp_path, reversed=True)), db, ui,
                               operator="ann", data_dir=tmp_path)
    assert status == "failed"
    (step, error, attempt) = ui.failures[0]
    assert step == "preflight" and "direction" in error and attempt == 1
    assert _steps(db, run_id) == [("preflight", 1, "failed")]
    assert "stop" in station_plugin.motor_calls


def test_failed_step_is_retried(
    tmp_path: Path, db: Database, station_plugin: StationTestPlugin
) -> None:
    station_plugin.strategy.failures = 1
    ui = ScriptedOperator(place=_stop_at("qa_cube"), decisions=["retry"])
    run_id, status = start_run(load_recipe(toy_recipe(tmp_path)), db, ui, operator="ann",
                               data_dir=tmp_path)
    assert status == "aborted"  # at the cube, by script
    steps = _steps(db, run_id)
    assert ("fine_tune", 1, "failed") in steps and ("fine_tune", 2, "passed") in steps
    assert ui.failures[0][0] == "fine_tune" and "scripted failure" in ui.failures[0][1]
    assert station_plugin.events.count(("fine_tune", "failed")) == 1


def test_resume_continues_at_the_first_unfinished_step(
    tmp_path: Path, db: Database, station_plugin: StationTestPlugin
) -> None:
    station_plugin.strategy.failures = 1
    loaded = load_recipe(toy_recipe(tmp_path))
    run_id, status = start_run(loaded, db, ScriptedOperator(), operator="ann", data_dir=tmp_path)
    assert status == "failed"
    with db.session() as s:
        before = {a.kind: (a.path, a.sha256) for a in s.query(Artifact).filter_by(run_id=run_id)}
    ui = ScriptedOperator(place=_stop_at("qa_cube"))
    assert resume_run(run_id, db, ui) == "aborted"
    steps = _steps(db, run_id)
    # the scans were not repeated; fine-tuning re-ran on the stored spin recording
    assert [s for s in steps if s[0] in ("static_scan", "spin_scan")] == [
        ("static_scan", 1, "passed"), ("spin_scan", 1, "passed")]
    assert ("fine_tune", 2, "passed") in steps
    assert ui.placed == ["qa_cube"]
    with db.session() as s:
        after = {a.kind: (a.path, a.sha256) for a in s.query(Artifact).filter_by(run_id=run_id)}
    assert after == before
    for path, sha in after.values():
        assert file_sha256(Path(path)) == sha


def test_resume_refuses_a_changed_recording(
    tmp_path: Path, db: Database, station_plugin: StationTestPlugin
) -> None:
    station_plugin.strategy.failures = 1
    run_id, _ = start_run(load_recipe(toy_recipe(tmp_path)), db, ScriptedOperator(),
                          operator="ann", data_dir=tmp_path)
    with db.session() as s:
        spin = s.query(Artifact).filter_by(run_id=run_id, kind="spin").one()
    with open(spin.path, "r+b") as f:
        f.seek(100)
        f.write(b"\x00\x01\x02")
    ui = ScriptedOperator()
    assert resume_run(run_id, db, ui) == "failed"
    assert "changed since it was stored" in ui.failures[-1][1]


def test_resume_of_unknown_or_passed_run(db: Database, station_plugin: StationTestPlugin) -> None:
    with pytest.raises(StationError, match="no run 99"):
        resume_run(99, db, ScriptedOperator())


def test_unknown_driver_is_refused_before_the_run(tmp_path: Path, db: Database) -> None:
    with plugins.isolated(sim_plugin), pytest.raises(RecipeError, match=r"station\.lidar\.driver"):
        start_run(load_recipe(toy_recipe(tmp_path)), db, ScriptedOperator(),
                  operator="ann", data_dir=tmp_path)
    with db.session() as s:
        assert s.query(Run).count() == 0


def test_machine_states_follow_the_workflow() -> None:
    assert STEPS == ("preflight", "place_static_target", "static_scan", "place_spin_target",
                     "spin_scan", "fine_tune", "place_qa_cube", "cube_scan", "report")
    assert next_in_order("fine_tune") == "place_qa_cube"
    assert next_in_order("report") == "done"
    # one step class per state, each under its own name
    assert tuple(REGISTRY) == STEPS
    assert all(step.name == name for name, step in REGISTRY.items())


def test_console_operator_prompts_and_abort(
    tmp_path: Path, db: Database, station_plugin: StationTestPlugin,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import io

    from rich.console import Console

    from calstation.cli._operator import ConsoleOperator

    # the operator continues after the static and spin targets, then types "a" at the cube
    monkeypatch.setattr("sys.stdin", io.StringIO("c\ncontinue\na\n"))
    out = io.StringIO()
    ui = ConsoleOperator(unattended=False, console=Console(file=out, width=120))
    run_id, status = start_run(load_recipe(toy_recipe(tmp_path)), db, ui, operator="bob",
                               data_dir=tmp_path)
    text = out.getvalue()
    assert status == "aborted"
    assert "Place the L-shaped static target" in text and "Place the QA cube" in text
    assert "Type continue (c) when it is placed" in text
    assert "ABORTED" in text and "place_qa_cube" not in [s[0] for s in _steps(db, run_id)
                                                         if s[2] == "passed"]
    assert station_plugin.motor_calls[-2:] == ["emergency_stop", "stop"]


def test_resume_refuses_a_run_another_live_process_executes(
    tmp_path: Path, db: Database, station_plugin: StationTestPlugin
) -> None:
    import socket
    import subprocess
    import sys

    station_plugin.strategy.failures = 1
    run_id, _ = start_run(load_recipe(toy_recipe(tmp_path)), db, ScriptedOperator(),
                          operator="ann", data_dir=tmp_path)
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        with db.session() as s:
            run = s.get(Run, run_id)
            assert run is not None and run.pid is not None
            run.status, run.pid, run.host = "running", other.pid, socket.gethostname()
        with pytest.raises(StationError, match=f"process {other.pid} on this host"):
            resume_run(run_id, db, ScriptedOperator())
        with db.session() as s:
            run = s.get(Run, run_id)
            assert run is not None
            run.host = "elsewhere"
        with pytest.raises(StationError, match="host 'elsewhere'"):
            resume_run(run_id, db, ScriptedOperator())
    finally:
        other.kill()
        other.wait()
    ui = ScriptedOperator(place=_stop_at("qa_cube"))
    assert resume_run(run_id, db, ui, force=True) == "aborted"




def test_station_on_postgresql(
    tmp_path: Path, postgres_url: str, station_plugin: StationTestPlugin
) -> None:
    """The same run, committed step by step into PostgreSQL, then resumed there."""
    database = open_database(postgres_url)
    try:
        station_plugin.strategy.failures = 1
        run_id, status = start_run(load_recipe(toy_recipe(tmp_path)), database,
                                   ScriptedOperator(), operator="pg", data_dir=tmp_path)
        assert status == "failed"
        assert resume_run(run_id, database, ScriptedOperator(place=_stop_at("qa_cube"))) \
            == "aborted"
        steps = _steps(database, run_id)
        assert ("fine_tune", 2, "passed") in steps and ("spin_scan", 1, "passed") in steps
        with database.session() as s:
            fine = s.query(Calibration).filter_by(run_id=run_id, stage="fine").one()
            assert fine.diagnostics is not None and fine.diagnostics["note"] == "toy"
            assert fine.sigma_ty is None and fine.sigma_tx == 1e-5
            for art in s.query(Artifact).filter_by(run_id=run_id):
                assert file_sha256(Path(art.path)) == art.sha256
    finally:
        database.dispose()


def test_ctrl_c_during_the_spin_scan_aborts_and_stops_the_motor(
    tmp_path: Path, db: Database, station_plugin: StationTestPlugin
) -> None:
    ui = ScriptedOperator(interrupt_in="spin scan")
    run_id, status = start_run(load_recipe(toy_recipe(tmp_path)), db, ui, operator="ann",
                               data_dir=tmp_path)
    assert status == "aborted"
    assert _steps(db, run_id)[-1] == ("spin_scan", 1, "aborted")
    # the acquisition stopped the spinning platter, then the station's abort: emergency stop
    assert station_plugin.motor_calls[-3:] == ["stop", "emergency_stop", "stop"]
    with db.session() as s:
        kinds = {a.kind: a.status for a in s.query(Artifact).filter_by(run_id=run_id)}
        run = s.get(Run, run_id)
        assert run is not None and run.status == "aborted" and run.finished_at is not None
        # the run records how the motor was stopped
        assert run.motor_stop is not None
        assert run.motor_stop["how"] == "emergency_stop then stop" and run.motor_stop["ok"]
        assert run.motor_stop["reason"] == "aborted"
    # the interrupted scan is kept as a partial recording, never as a finished one
    assert kinds == {"static": "complete", "spin": "partial"}
    assert ui.summaries[-1]["status"] == "aborted"
    assert any("motor stopped by emergency_stop then stop" in m for m in ui.messages)


def test_a_targetless_run_takes_no_l_target_and_resumes_in_its_own_steps(
    tmp_path: Path, db: Database, station_plugin: StationTestPlugin
) -> None:
    path = toy_recipe(tmp_path)
    data = yaml.safe_load(path.read_text())
    data["calibration"]["start"] = "platter"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    ui = ScriptedOperator(place=_stop_at("qa_cube"))
    run_id, status = start_run(load_recipe(path), db, ui, operator="ann", data_dir=tmp_path)
    assert status == "aborted"
    assert _steps(db, run_id) == [
        ("preflight", 1, "passed"), ("place_spin_target", 1, "passed"),
        ("spin_scan", 1, "passed"), ("fine_tune", 1, "passed"), ("place_qa_cube", 1, "aborted"),
    ]
    assert ui.placed == ["spin_target", "qa_cube"]
    assert any(m.startswith("  start from the platter") for m in ui.messages)
    with db.session() as s:
        kinds = {a.kind for a in s.query(Artifact).filter_by(run_id=run_id)}
        (fine,) = s.query(Calibration).filter_by(run_id=run_id).all()
        start = (fine.diagnostics or {})["start"]
    assert kinds == {"spin"} and fine.stage == "fine"
    # the toy strategy moved the platter's start by 0.1 mm, from each tz candidate (0, ±|tz|)
    assert fine.tx == pytest.approx(start["H"]["tx"] + 1e-4)
    assert start["strategy"] == "platter" and len(start["candidates"]) in (1, 3)
    # resumed: it goes on at the cube's placement, within the targetless steps
    ui2 = ScriptedOperator()
    resume_run(run_id, db, ui2)  # the toy's start is mm off: its cube check may fail
    assert ui2.placed == ["qa_cube"]
    assert [name for name, _, _ in _steps(db, run_id)][5:7] == ["place_qa_cube", "cube_scan"]


def test_ctrl_c_during_the_second_pass_keeps_the_first_as_complete(
    tmp_path: Path, db: Database, station_plugin: StationTestPlugin
) -> None:
    path = toy_recipe(tmp_path)
    data = yaml.safe_load(path.read_text())
    data["steps"]["spin_scan"]["second_pass_rpm"] = -60
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    ui = ScriptedOperator(interrupt_in="spin-pass2 scan")
    run_id, status = start_run(load_recipe(path), db, ui, operator="ann", data_dir=tmp_path)
    assert status == "aborted"
    assert _steps(db, run_id)[-1] == ("spin_scan", 1, "aborted")
    assert "spin scan" in ui.progress_titles and "spin-pass2 scan" in ui.progress_titles
    with db.session() as s:
        arts = {a.kind: (a.status, a.path, a.sha256) for a in
                s.query(Artifact).filter_by(run_id=run_id)}
    # the first pass had finished: kept whole; the second was cut short
    assert {k: v[0] for k, v in arts.items()} == {
        "static": "complete", "spin": "complete", "spin-pass2": "partial"}
    assert file_sha256(Path(arts["spin"][1])) == arts["spin"][2]


def test_resume_after_a_kill_in_the_second_pass_registers_both_recordings(
    tmp_path: Path, db: Database
) -> None:
    """A process killed during the second pass: recovery stores the first pass as complete and
    the second as partial (calstation.storage.db.journal)."""
    import socket
    import subprocess

    from calstation.storage.db import Station as StationRow
    from calstation.storage.db.journal import recover

    dead = subprocess.Popen(["true"])
    dead.wait()

    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "spin.mcap").write_bytes(b"first pass")
    (run_dir / "spin-pass2.mcap").write_bytes(b"second, cut short")
    with db.session() as s:
        station = StationRow(name="st")
        s.add(station)
        s.flush()
        run = Run(station_id=station.id, recipe_name="r", recipe_path="r.yaml", recipe_text="",
                  recipe_sha256="0" * 64, operator="o", unattended=True, data_dir=str(run_dir),
                  status="running", host=socket.gethostname(), pid=dead.pid)
        s.add(run)
        s.flush()
        s.add(Step(run_id=run.id, name="spin_scan", attempt=1, status="running"))
        run_id = run.id
    recover(db)
    with db.session() as s:
        kinds = {a.kind: a.status for a in s.query(Artifact).filter_by(run_id=run_id)}
    assert kinds == {"spin": "complete", "spin-pass2": "partial"}


def _qa_recipe(tmp_path: Path, name: str, seed: int = 0, **qa: Any) -> Path:
    """The lean recipe with its qa section replaced by ``qa`` (and the simulation's seed)."""
    path = toy_recipe(tmp_path)
    data = yaml.safe_load(path.read_text())
    data["qa"] = qa
    data["simulation"]["seed"] = seed
    out = tmp_path / name
    out.write_text(yaml.safe_dump(data, sort_keys=False))
    return out


def test_failed_cube_check_offers_reseat_and_rescan(
    tmp_path: Path, db: Database, station_plugin: StationTestPlugin
) -> None:
    # a limit no cube meets: the check fails, the operator re-seats once, then gives up
    ui = ScriptedOperator(decisions=["retry", "abort"])
    run_id, status = start_run(load_recipe(_qa_recipe(tmp_path, "strict.yaml", edge_error=2e-6)),
                               db, ui, operator="ann", data_dir=tmp_path, serial="UNIT-42")
    assert status == "failed"
    assert [f[0] for f in ui.failures] == ["cube_scan", "cube_scan"]
    assert "cube check failed" in ui.failures[0][1]
    assert ui.placed.count("qa_cube") == 2  # placed, then re-seated for the rescan
    steps = _steps(db, run_id)
    assert ("cube_scan", 1, "failed") in steps and ("cube_scan", 2, "failed") in steps
    assert steps[-1] == ("report", 1, "passed")
    with db.session() as s:
        run = s.get(Run, run_id)
        assert run is not None
        assert run.error is not None and run.error.startswith("cube check failed")
        assert len(run.cube_checks) == 2 and not any(c.passed for c in run.cube_checks)
        assert [a.kind for a in run.artifacts].count("cube") == 2  # both scans kept
        assert run.unit_serial == "UNIT-42"  # the operator's serial wins over the lidar's
        report = json.loads((Path(run.data_dir) / "report.json").read_text())
    assert report["status"] == "failed" and report["unit_serial"] == "UNIT-42"
    # said, since this lidar's driver is not the simulator (whose serial names no unit)
    assert any("the lidar reports serial 'sim-" in m and "'UNIT-42'; the operator's is kept"
               in m for m in ui.messages), ui.messages


def test_drift_beyond_limits_fails_the_run_when_the_recipe_says_so(
    tmp_path: Path, db: Database, station_plugin: StationTestPlugin
) -> None:
    loose = dict(edge_error=0.05, obb_edge_error=0.05, flatness_rms=0.05,
                 perpendicularity_deg=10.0, twist_deg=10.0)
    first, status = start_run(load_recipe(_qa_recipe(tmp_path, "a.yaml", **loose)), db,
                              ScriptedOperator(), operator="ann", data_dir=tmp_path)
    assert status == "passed"
    # another seed: other noise, so a slightly different calibration of the same station
    strict = _qa_recipe(tmp_path, "b.yaml", seed=7, **loose, drift_translation=1e-6,
                        drift_rotation_deg=0.001, drift_fails=True)
    second, status = start_run(load_recipe(strict), db, ScriptedOperator(), operator="ann",
                               data_dir=tmp_path)
    assert status == "failed"
    with db.session() as s:
        run = s.get(Run, second)
        assert run is not None and run.error is not None
        assert f"drifted beyond the recipe's limits since run {first}" in run.error
        assert not any(c.accepted for c in run.calibrations)
        # the lidar's own serial is the unit's when the operator gives none
        (preflight,) = [st for st in run.steps if st.name == "preflight"]
        assert preflight.result is not None
        assert run.unit_serial == preflight.result["lidar"]["serial"] == "sim-7"
        assert preflight.result["unit_serial"] == "sim-7"


def test_a_targetless_recipe_drops_the_l_target_steps_everywhere() -> None:
    from calstation.station.steps import TARGETLESS_DROPS, run_steps
    from calstation.web.live import LiveState

    targetless = load_recipe(RECIPES / "sim-targetless.yaml").recipe
    steps = run_steps(targetless)
    assert steps == tuple(s for s in STEPS if s not in TARGETLESS_DROPS)
    assert run_steps(load_recipe(RECIPES / "sim-periodicity.yaml").recipe) == STEPS
    live = LiveState()
    live.begin(1, "sim-targetless", "ann", None, steps)
    assert tuple(live.steps) == steps  # the operator page lists only the steps the run takes


def test_the_runs_end_is_stored_then_told_to_each_observer_in_turn(
    tmp_path: Path, db: Database, station_plugin: StationTestPlugin
) -> None:
    """Storing comes first; the observers see the stored summary, in order; one that raises is
    a warning naming it, and the next is told all the same."""
    from calstation.station.machine import Station
    from calstation.station.observers import RunEnded
    from calstation.station.runs import create_run

    seen: list[tuple[str, RunEnded]] = []

    def first(ended: RunEnded) -> None:
        with db.session() as s:  # stored before any observer is told
            run = s.get(Run, ended.run_id)
            assert run is not None
            seen.append(("first", ended) if run.status == ended.status else ("unstored", ended))

    def broken(ended: RunEnded) -> None:
        raise OSError("disk full")

    def last(ended: RunEnded) -> None:
        seen.append(("last", ended))

    loaded = load_recipe(toy_recipe(tmp_path))
    ui = ScriptedOperator(place=_stop_at("spin_target"))
    run_id = create_run(loaded, db, operator="ann", unattended=True, data_dir=tmp_path)
    status = Station(db, run_id, loaded, ui, observers=[first, broken, last]).run()
    assert status == "aborted"
    assert [name for name, _ in seen] == ["first", "last"]
    ended = seen[0][1]
    assert ended.run_id == run_id and ended.status == "aborted" and ended.error
    assert ended.summary["id"] == run_id and ended.summary["status"] == "aborted"
    assert any("broken failed at the end of run" in m and "disk full" in m for m in ui.messages)
    # only the observers given were told: no summary printed, no plugin hook
    assert ui.summaries == [] and ("run", "aborted") not in station_plugin.events
    assert station_plugin.motor_calls[-2:] == ["emergency_stop", "stop"]


def test_no_step_that_computes_begins_while_the_engine_is_still_being_imported(
    tmp_path: Path, db: Database, station_plugin: StationTestPlugin,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Two threads importing one module can deadlock in Python's import locks (a loaded
    machine's run failed its spin scan on scipy.spatial so): the placements run beside the
    engine's import in the background, the scans and the fitting after it."""
    order: list[str] = []
    scanning = threading.Event()

    class Ui(UnattendedOperator):
        def event(self, event: Any) -> None:
            super().event(event)
            if event.kind == "step_started":
                order.append(event.data["step"])
                if event.data["step"] == "static_scan":
                    scanning.set()

    def slow_preload() -> threading.Thread:
        def load() -> None:
            scanning.wait(timeout=2.0)  # a loaded machine: still importing when a scan could
            order.append("preload done")

        thread = threading.Thread(target=load, daemon=True)
        thread.start()
        return thread

    monkeypatch.setattr("calstation.station.machine.preload_engine", slow_preload)
    run_id, status = start_run(load_recipe(toy_recipe(tmp_path)), db, Ui(), operator="ann",
                               data_dir=tmp_path / "data")
    assert status == "passed", _steps(db, run_id)
    done = order.index("preload done")
    assert order[:done] == ["preflight", "place_static_target"], order
    assert order[done + 1] == "static_scan", order


def test_a_cube_check_that_could_not_measure_the_perpendicularity_is_stored_as_not_measured(
    tmp_path: Path, db: Database, station_plugin: StationTestPlugin,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A cube scan that saw no two adjacent side faces has no perpendicularity: the check's end
    is stored with it NULL (the column refused it, and the run was interrupted), and the run's
    summary gives it as None beside the measures that were made."""
    import math

    from calstation.storage.report import run_summary

    monkeypatch.setattr("calstation.engine.cube._perpendicularity",
                        lambda faces, pts: (math.nan, math.nan))
    run_id, status = start_run(load_recipe(toy_recipe(tmp_path)), db, UnattendedOperator(),
                               operator="ann", data_dir=tmp_path / "data")
    assert status == "passed", _steps(db, run_id)
    with db.session() as s:
        run = s.get(Run, run_id)
        assert run is not None
        cube = run_summary(run)["cube_check"]
    assert cube is not None and cube["perpendicularity_deg"] is None
    assert cube["edge_error"] is not None and math.isfinite(cube["edge_error"])


def test_a_scan_whose_lidar_lost_lines_is_named_to_the_operator(
    tmp_path: Path, db: Database, station_plugin: StationTestPlugin
) -> None:
    """A lidar stream that loses 150 lines of each spin scan (a network dropping packets): the
    operator is told, per scan, how many of its lines never arrived and the longest gap; the
    static scan, which lost none of its 40, is not named."""
    path = toy_recipe(tmp_path)
    data = yaml.safe_load(path.read_text())
    data["station"]["lidar"]["settings"] = {"lose_lines": [300, 150]}
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    ui = UnattendedOperator()
    run_id, status = start_run(load_recipe(path), db, ui, operator="t",
                               data_dir=tmp_path / "data")
    with db.session() as s:
        results = {st.name: st.result for st in s.query(Step).filter_by(run_id=run_id)}
    assert results["spin_scan"]["lost_lines"] == results["cube_scan"]["lost_lines"] == 150
    lost = [m for m in ui.messages if "lidar lines" in m]
    assert [m.split(" lost ")[0] for m in lost] == ["the spin scan", "the cube scan"], lost
    for message in lost:
        assert " lost 150 of its " in message and "the longest gap 0.15" in message, message
    assert status == "passed", ui.failures
