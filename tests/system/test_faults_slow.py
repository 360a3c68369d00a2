"""Fault injection, the long cases (``-m slow``): whole runs of the simulated station through the
CLI, with a database locked for 30 s mid-run, two runs started together on a fresh database (two
stations, and one station twice), a SIGKILL at every step, and recipes at the edges of the
accepted ranges.
"""

from __future__ import annotations

import signal
import sqlite3
import subprocess
import time
from pathlib import Path

import pytest
import yaml

from calstation.recipes import load_recipe
from calstation.recordings.runfolder import file_sha256
from calstation.station.runs import wait_for_step
from calstation.station.steps import STEPS
from calstation.storage.db import Artifact, Database, Run, Step
from calstation.testing import lean_recipe
from tests.support.clirun import cli_argv, cli_env

pytestmark = pytest.mark.slow
pytest.importorskip("calstation_sim")


def _wait_for(db: Database, run_id: int, step: str, proc: subprocess.Popen[str],
              timeout_s: float = 300) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and proc.poll() is None:
        try:
            if wait_for_step(db, run_id, step, timeout_s=0.5):
                return
        except Exception:  # the database may not exist yet
            time.sleep(0.2)
    raise AssertionError(f"step {step} never started (exit code {proc.poll()})")


def _all_stored(db: Database, run_id: int) -> None:
    with db.session() as s:
        run = s.get(Run, run_id)
        assert run is not None and run.status == "passed", run and run.error
        steps = [(st.name, st.status) for st in
                 s.query(Step).filter_by(run_id=run_id).order_by(Step.id)]
        arts = s.query(Artifact).filter_by(run_id=run_id, status="complete").all()
    assert {n for n, st in steps if st == "passed"} == set(STEPS), steps
    assert "running" not in {st for _, st in steps}
    assert [n for n, st in steps if st == "passed" and not n.startswith("place_")] == [
        n for n in STEPS if not n.startswith("place_")], steps  # each once, in order
    assert {a.kind for a in arts} == {"static", "spin", "cube", "report", "calibration"}
    for a in arts:
        assert file_sha256(Path(a.path)) == a.sha256


def test_database_locked_for_30_s_mid_run_ends_pass_with_every_step(tmp_path: Path) -> None:
    db_path = tmp_path / "locked.db"
    url = f"sqlite:///{db_path}"
    proc = subprocess.Popen(cli_argv("run", str(lean_recipe(tmp_path)), "--yes", "--db", url),
                            env=cli_env(tmp_path), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    db = Database(url)
    try:
        _wait_for(db, 1, "spin_scan", proc)
        conn = sqlite3.connect(db_path, isolation_level=None, timeout=60)
        conn.execute("BEGIN IMMEDIATE")  # another process holds the write lock for 30 s
        time.sleep(30)
        conn.execute("COMMIT")
        conn.close()
        out, err = proc.communicate(timeout=600)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, out[-3000:] + err[-3000:]
    assert "waiting for the database" in out + err
    assert "Traceback" not in out + err
    _all_stored(db, 1)
    db.dispose()


def _station(recipe: Path, station_id: str) -> Path:
    """``recipe`` for the station ``station_id``, written beside it."""
    data = yaml.safe_load(recipe.read_text())
    data["station"]["id"] = station_id
    path = recipe.with_name(f"{station_id}.yaml")
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


@pytest.mark.parametrize("fresh", [True, False], ids=["fresh database", "existing database"])
def test_two_runs_started_together_both_end_stored(tmp_path: Path, fresh: bool) -> None:
    """Two stations sharing one database (fresh: both create its schema at once) start a run
    each at the same moment: both pass with every step stored."""
    url = f"sqlite:///{tmp_path / 'shared.db'}"
    lean = lean_recipe(tmp_path)
    if not fresh:
        Database(url).ensure_schema()
    env = cli_env(tmp_path)
    procs = [subprocess.Popen(cli_argv("run", str(_station(lean, f"sim-0{k}")), "--yes", "--db",
                                       url), env=env, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True)
             for k in (1, 2)]
    outputs = [p.communicate(timeout=900) for p in procs]
    for p, (out, err) in zip(procs, outputs, strict=True):
        assert p.returncode == 0, out[-3000:] + err[-3000:]
        assert "Traceback" not in out + err
    db = Database(url)
    for run_id in (1, 2):
        _all_stored(db, run_id)
    db.dispose()


def test_two_runs_started_together_on_one_station_one_is_refused(tmp_path: Path) -> None:
    """One station, two runs at once: one turntable, so one run passes and the other is refused
    with a message that names the run holding the station, and stores no run."""
    url = f"sqlite:///{tmp_path / 'shared.db'}"
    recipe = lean_recipe(tmp_path)
    procs = [subprocess.Popen(cli_argv("run", str(recipe), "--yes", "--db", url),
                              env=cli_env(tmp_path), stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True)
             for _ in range(2)]
    outputs = [p.communicate(timeout=900) for p in procs]
    codes = sorted(p.returncode for p in procs)
    assert codes == [0, 4], outputs
    refused = next(out + err for p, (out, err) in zip(procs, outputs, strict=True)
                   if p.returncode == 4)
    assert "is in use: run 1" in refused and "Traceback" not in refused
    db = Database(url)
    _all_stored(db, 1)
    with db.session() as s:
        assert s.query(Run).count() == 1
    db.dispose()


def _real_time(recipe: Path) -> Path:
    """``recipe`` with its simulated station on the host's clock: every step takes the time it
    takes at a real station (the preflight's spin-up ~2 s), long enough to be hit."""
    data = yaml.safe_load(recipe.read_text())
    for device in ("lidar", "turntable", "encoder"):
        data["station"][device].setdefault("settings", {})["real_time"] = True
    recipe.write_text(yaml.safe_dump(data, sort_keys=False))
    return recipe


# the placements (unattended) and the report take milliseconds: too brief to be hit reliably
@pytest.mark.parametrize("step", ["preflight", "static_scan", "spin_scan", "fine_tune",
                                  "cube_scan"])
def test_sigkill_at_every_step_resumes_to_pass(tmp_path: Path, step: str) -> None:
    url = f"sqlite:///{tmp_path / 'kill.db'}"
    env = cli_env(tmp_path)
    recipe = _real_time(lean_recipe(tmp_path))
    proc = subprocess.Popen(cli_argv("run", str(recipe), "--yes", "--db", url),
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    db = Database(url)
    try:
        _wait_for(db, 1, step, proc)  # type: ignore[arg-type]
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    with db.session() as s:
        before = {(a.kind, a.sha256) for a in s.query(Artifact).filter_by(run_id=1)}
    resumed = subprocess.run(cli_argv("resume", "1", "--yes", "--db", url), env=env,
                             capture_output=True, text=True, timeout=900)
    assert resumed.returncode == 0, resumed.stdout[-3000:] + resumed.stderr[-3000:]
    _all_stored(db, 1)
    with db.session() as s:
        after = {(a.kind, a.sha256) for a in s.query(Artifact).filter_by(run_id=1)}
    assert before <= after  # no recording lost or changed
    db.dispose()


EDGES = {
    "slowest spin the budget allows": {"steps": {"spin_scan": {"rpm": 7, "revolutions": 1.0},
                                                 "cube_scan": {"rpm": 7, "revolutions": 1.0}}},
    "fastest spin": {"steps": {"spin_scan": {"rpm": 120}, "cube_scan": {"rpm": 120}}},
    "fewest static lines": {"steps": {"static_scan": {"lines": 10}}},
    "noisiest lidar": {"simulation": {"lidar": {"range_noise": 0.1}}},
    "largest placement error": {"simulation": {"placement": {"position_sigma": 0.05,
                                                             "yaw_sigma_deg": 10}}},
    "frustum near its build limit": {"fixtures": {"spin_target": {"height": 0.058}}},
    "cube at the platter's edge": {"fixtures": {"qa_cube": {"offset": [0.21, 0.0]}}},
    "no ripple, no settle": {"simulation": {"turntable": {"speed_ripple": 0}},
                             "steps": {"spin_scan": {"settle_s": 0}}},
}


def _merge(base: dict[str, object], edit: dict[str, object]) -> None:
    for key, value in edit.items():
        if isinstance(value, dict) and isinstance(base.get(key), dict):
            _merge(base[key], value)  # type: ignore[arg-type]
        else:
            base[key] = value


@pytest.mark.parametrize("name", list(EDGES))
def test_recipes_at_the_edges_validate_and_run_to_their_end(tmp_path: Path, name: str) -> None:
    data = yaml.safe_load(lean_recipe(tmp_path).read_text())
    _merge(data, EDGES[name])
    path = tmp_path / "edge.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    load_recipe(path)  # validate accepts it
    url = f"sqlite:///{tmp_path / 'edge.db'}"
    proc = subprocess.run(cli_argv("run", str(path), "--yes", "--db", url), env=cli_env(tmp_path),
                          capture_output=True, text=True, timeout=900)
    # its end: passed, or failed with a clear message (never a traceback, a hang or running)
    assert proc.returncode in (0, 1), proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "Traceback" not in proc.stdout + proc.stderr
    db = Database(url)
    with db.session() as s:
        run = s.get(Run, 1)
        assert run is not None and run.status in ("passed", "failed")
        assert run.finished_at is not None
    db.dispose()
