"""One run per station, whatever starts it: the station lock (calstation/station/lock.py).

The lock is taken by ``calstation run``, ``resume`` and the web station before a run is created;
a second start is refused naming who holds the station, from where and since when; a lock left by
a process that died is detected (its process is gone, or on another host its heartbeat stopped)
and taken over, never waited on.
"""

from __future__ import annotations

import datetime as dt
import multiprocessing
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from calstation.recipes import load_recipe
from calstation.station import lock as lock_mod
from calstation.station.lock import Holder, StationBusy, station_holder, take_station
from calstation.station.runs import resume_run, start_run
from calstation.storage.db import Database, Run, StationLock, utcnow
from calstation.web.app import create_app
from tests.support.clirun import run_cli

pytest.importorskip("calstation_sim")
from tests.support.station import ScriptedOperator, StationTestPlugin, toy_recipe

REPO = Path(__file__).resolve().parents[2]


def _holder(operator: str = "ann", front_end: str = "calstation run in terminal /dev/pts/7"
            ) -> Holder:
    return Holder.here(operator, front_end)


def test_a_second_take_is_refused_naming_who_where_and_since_when(db: Database) -> None:
    with take_station(db, "bench-1", _holder()):
        with pytest.raises(StationBusy) as refused:
            take_station(db, "bench-1", _holder("bob", "the web station at http://x/"))
        message = str(refused.value)
        assert "station bench-1 is in use" in message
        assert "operator ann" in message
        assert "calstation run in terminal /dev/pts/7" in message
        assert f"host {socket.gethostname()}" in message and f"process {os.getpid()}" in message
        assert "since" in message and "UTC" in message
        assert refused.value.holder["operator"] == "ann"
        assert refused.value.exit_code == 4
        # another station is free
        with take_station(db, "bench-2", _holder("bob")):
            pass
    # released: free again, and nothing is left behind
    with take_station(db, "bench-1", _holder("bob")):
        assert station_holder(db, "bench-1")["operator"] == "bob"  # type: ignore[index]
    assert station_holder(db, "bench-1") is None


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def _plant(db: Database, station: str, **fields: Any) -> None:
    """A lock row as another process would have left it."""
    from calstation.storage.db import get_or_create_station

    sid = get_or_create_station(db, station)
    now = utcnow()
    row = {"token": "t" * 32, "operator": "carl", "front_end": "calstation run (no terminal)",
           "host": socket.gethostname(), "pid": 1, "process_started": None,
           "acquired_at": now, "heartbeat_at": now, **fields}
    with db.session() as s:
        s.add(StationLock(station_id=sid, **row))


def test_a_lock_left_by_a_dead_process_is_taken_over_and_said(db: Database) -> None:
    _plant(db, "bench-1", pid=_dead_pid())
    with take_station(db, "bench-1", _holder()) as hold:
        assert hold.taken_over is not None and hold.taken_over["operator"] == "carl"
        note = lock_mod.taken_over_note(hold.taken_over)
        assert "calstation run (no terminal)" in note and "which has ended" in note


def test_a_reused_process_id_is_not_taken_for_the_holder(db: Database) -> None:
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        started = lock_mod.process_start(other.pid)
        _plant(db, "bench-1", pid=other.pid, process_started=started)
        with pytest.raises(StationBusy):  # alive, and the same process
            take_station(db, "bench-1", _holder())
        if started is None:
            pytest.skip("this system does not say when a process started")
        with db.session() as s:
            row = s.scalars(select(StationLock)).one()
            row.process_started = "another:process"
        with take_station(db, "bench-1", _holder()) as hold:  # the id now names another
            assert hold.taken_over is not None
    finally:
        other.kill()
        other.wait()


def test_a_holder_on_another_host_is_stale_once_its_heartbeat_stops(db: Database) -> None:
    _plant(db, "bench-1", host="bench-pc-2", pid=4242)
    with pytest.raises(StationBusy, match="on host bench-pc-2 \\(process 4242\\)"):
        take_station(db, "bench-1", _holder())
    old = utcnow() - dt.timedelta(seconds=lock_mod.STALE_AFTER_S + 5)
    with db.session() as s:
        row = s.scalars(select(StationLock)).one()
        row.heartbeat_at = old
    with take_station(db, "bench-1", _holder()) as hold:
        assert hold.taken_over is not None and hold.taken_over["host"] == "bench-pc-2"


def test_the_holder_renews_its_heartbeat(db: Database, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(lock_mod, "HEARTBEAT_S", 0.05)
    with take_station(db, "bench-1", _holder()):
        first = station_holder(db, "bench-1")["heartbeat_at"]  # type: ignore[index]
        deadline = time.monotonic() + 600  # a hang guard: the renewal ends the wait
        while station_holder(db, "bench-1")["heartbeat_at"] == first:  # type: ignore[index]
            assert time.monotonic() < deadline, "the heartbeat was not renewed"
            time.sleep(0.1)


def _take_and_sleep(url: str, station: str, ready: Any) -> None:
    """Take the station and hold it until this process is killed (the tests kill it)."""
    database = Database(url)
    take_station(database, station, Holder.here("kim", "calstation run (no terminal)"))
    ready.set()
    threading.Event().wait()


def test_a_holder_killed_with_sigkill_leaves_a_lock_the_next_start_takes(tmp_path: Path,
                                                                         db: Database) -> None:
    ctx = multiprocessing.get_context("spawn")
    ready = ctx.Event()
    proc = ctx.Process(target=_take_and_sleep, args=(db.url, "bench-1", ready))
    proc.start()
    try:
        assert ready.wait(600)
        with pytest.raises(StationBusy, match="operator kim"):
            take_station(db, "bench-1", _holder())
        os.kill(proc.pid, signal.SIGKILL)
        proc.join(600)
        with take_station(db, "bench-1", _holder()) as hold:
            assert hold.taken_over is not None and hold.taken_over["pid"] == proc.pid
    finally:
        if proc.is_alive():
            proc.kill()


def _race(url: str, start: Any, done: Any, out: Any) -> None:
    database = Database(url)
    out.put("ready")
    start.wait()
    try:
        take_station(database, "bench-1", Holder.here(f"p{os.getpid()}", "race"))
        out.put("took")
        done.wait()  # hold it until every other process has tried
    except StationBusy:
        out.put("refused")


def test_of_simultaneous_starts_exactly_one_takes_the_station(db: Database) -> None:
    ctx = multiprocessing.get_context("spawn")
    start, done, out = ctx.Event(), ctx.Event(), ctx.Queue()
    procs = [ctx.Process(target=_race, args=(db.url, start, done, out)) for _ in range(4)]
    for p in procs:
        p.start()
    try:
        assert [out.get(timeout=600) for _ in procs] == ["ready"] * 4  # all imported
        start.set()
        answers = sorted(out.get(timeout=600) for _ in procs)
    finally:
        done.set()
        for p in procs:
            p.join(600)
    assert answers == ["refused", "refused", "refused", "took"]


# --- the front ends ------------------------------------------------------------------------
def _page_headers(client: TestClient, origin: str) -> dict[str, str]:
    """What the operator page's script sends with a state change (as the web API's tests)."""
    from tests.support.webapi import csrf_of

    return {**csrf_of(client), "Origin": origin}


def test_run_is_refused_while_another_process_holds_the_station(
    tmp_path: Path, db: Database, capsys: pytest.CaptureFixture[str],
    station_plugin: StationTestPlugin,
) -> None:
    recipe = toy_recipe(tmp_path)
    ctx = multiprocessing.get_context("spawn")
    ready = ctx.Event()
    proc = ctx.Process(target=_take_and_sleep, args=(db.url, "sim-test", ready))
    proc.start()
    try:
        assert ready.wait(600)
        code, out, err = run_cli(["run", str(recipe), "--yes", "--db", db.url,
                                  "--data-dir", str(tmp_path)], capsys)
        assert code == 4, out + err
        assert "station sim-test is in use" in err and "operator kim" in err
        assert "Traceback" not in out + err
        with db.session() as s:  # refused before any run was created
            assert s.scalars(select(Run)).first() is None
    finally:
        proc.kill()
        proc.join(600)
    # the holder is gone: the next run takes the station over, says so, and passes
    code, out, err = run_cli(["run", str(recipe), "--yes", "--db", db.url,
                              "--data-dir", str(tmp_path)], capsys)
    assert code == 0, out + err
    assert "which has ended: its lock is cleared" in " ".join((out + err).split())
    assert station_holder(db, "sim-test") is None


def test_resume_takes_the_station_too(tmp_path: Path, db: Database,
                                      station_plugin: StationTestPlugin) -> None:
    loaded = load_recipe(toy_recipe(tmp_path))
    run_id, status = start_run(loaded, db, ScriptedOperator(place=lambda f: f != "qa_cube"),
                               operator="ann", data_dir=tmp_path)
    assert status == "aborted"
    bob = _holder("bob", "the web station at http://127.0.0.1:8470/")
    with take_station(db, "sim-test", bob), pytest.raises(StationBusy, match="operator bob"):
        resume_run(run_id, db, ScriptedOperator())
    assert resume_run(run_id, db, ScriptedOperator()) == "passed"


def test_the_web_station_refuses_a_start_while_a_terminal_holds_the_station(
    tmp_path: Path, db: Database, station_plugin: StationTestPlugin
) -> None:
    (tmp_path / "recipes").mkdir()
    recipe = toy_recipe(tmp_path / "recipes")
    app = create_app(db, data_dir=tmp_path / "data", recipes_dir=recipe.parent)
    client = TestClient(app, base_url="http://127.0.0.1:8470")
    headers = _page_headers(client, "http://127.0.0.1:8470")
    with take_station(db, "sim-test", _holder("kim", "calstation run in terminal /dev/pts/3")):
        r = client.post("/api/start", json={"recipe": recipe.name, "operator": "ann"},
                        headers=headers)
        assert r.status_code == 409, r.text
        assert "operator kim" in r.json()["error"]
        assert "calstation run in terminal /dev/pts/3" in r.json()["error"]
        assert client.get("/state.json").json()["status"] == "idle"


def test_two_web_stations_over_one_database_run_one_run_at_a_time(
    tmp_path: Path, db: Database, station_plugin: StationTestPlugin
) -> None:
    (tmp_path / "recipes").mkdir()
    recipe = toy_recipe(tmp_path / "recipes")
    first = create_app(db, data_dir=tmp_path / "data", recipes_dir=recipe.parent)
    second = create_app(db, data_dir=tmp_path / "data", recipes_dir=recipe.parent)
    a = TestClient(first, base_url="http://127.0.0.1:8470")
    b = TestClient(second, base_url="http://127.0.0.1:8471")
    r = a.post("/api/start", json={"recipe": recipe.name, "operator": "ann"},
               headers=_page_headers(a, "http://127.0.0.1:8470"))
    assert r.status_code == 201, r.text
    try:
        r = b.post("/api/start", json={"recipe": recipe.name, "operator": "bob"},
                   headers=_page_headers(b, "http://127.0.0.1:8471"))
        assert r.status_code == 409, r.text
        assert "the web station at http://127.0.0.1:8470/" in r.json()["error"]
        assert "operator ann" in r.json()["error"]
    finally:
        first.state.runner.abort("test over")
        assert first.state.runner.join(600)
    assert station_holder(db, "sim-test") is None
