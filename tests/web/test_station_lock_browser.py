"""One run per station in a real browser: the web station and ``calstation run`` in another
process (as in a terminal) on the same station; exactly one proceeds, and the other is refused
naming who holds the station.

Run with ``pytest -m browser`` (``make test`` does).
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import func, select

from calstation import plugins
from calstation.station.lock import station_holder
from calstation.storage.db import Database, Run
from tests.support.webpage import click_answer, place, start, station
from tests.support.webstation import CHROMIUM, HANG_S, copy_recipe, wait_until

calstation_sim = pytest.importorskip("calstation_sim")
from calstation_sim import plugin as sim_plugin  # noqa: E402

REPO = Path(__file__).resolve().parents[2]

pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(not Path(CHROMIUM).exists(),
                       reason=f"{CHROMIUM} missing: run scripts/system-deps.sh"),
]


def _env(tmp_path: Path) -> dict[str, str]:
    env = dict(os.environ, CALSTATION_HOME=str(tmp_path / "home"), COLUMNS="400")
    env["PYTHONPATH"] = os.pathsep.join(
        [str(REPO), str(REPO / "plugins" / "calstation-sim"), env.get("PYTHONPATH", "")])
    return env


def _terminal_run(tmp_path: Path, database: Database, recipe: Path, *, yes: bool) -> Any:
    """``calstation run`` in a process of its own (stdin a pipe: without ``--yes`` it waits at
    its first placement for an Enter that never comes)."""
    args = [sys.executable, "-m", "calstation", "run", str(recipe), "--db", database.url,
            "--data-dir", str(tmp_path / "terminal"), "--operator", "kim"]
    return subprocess.Popen(args + (["--yes"] if yes else []), env=_env(tmp_path),
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _runs(database: Database) -> int:
    with database.session() as s:
        return int(s.scalar(select(func.count()).select_from(Run)) or 0)


@pytest.fixture
def sim_recipe(tmp_path: Path) -> Iterator[Path]:
    recipe = copy_recipe(REPO / "recipes" / "sim-periodicity.yaml", tmp_path / "recipes")
    with plugins.isolated(sim_plugin):
        yield recipe


def test_a_web_run_holds_the_station_against_a_terminal_run(
    tmp_path: Path, db: Database, page: Any, sim_recipe: Path
) -> None:
    with station(tmp_path, db, sim_recipe) as url:
        start(page, url, sim_recipe.name, operator="ann")
        place(page, "static_target")  # the web run waits at its first placement
        terminal = _terminal_run(tmp_path, db, sim_recipe, yes=True)
        out, err = terminal.communicate(timeout=HANG_S)
        assert terminal.returncode == 4, out + err
        said = " ".join(err.split())
        assert "station sim-01 is in use" in said and "operator ann" in said, said
        assert f"the web station at {url}/" in said and "since" in said
        assert "Traceback" not in out + err
        assert _runs(db) == 1  # the terminal created no run
        # the web run goes on, unharmed
        click_answer(page, "continue")
        place(page, "spin_target")
        page.click("#abort-button")
        page.wait_for_selector("#verdict")
    assert station_holder(db, "sim-01") is None


def test_a_terminal_run_holds_the_station_against_the_web_station(
    tmp_path: Path, db: Database, page: Any, sim_recipe: Path
) -> None:
    terminal = _terminal_run(tmp_path, db, sim_recipe, yes=False)
    try:
        wait_until(lambda: station_holder(db, "sim-01") is not None
                   and station_holder(db, "sim-01")["run_id"] is not None)
        run_id = station_holder(db, "sim-01")["run_id"]  # type: ignore[index]
        with station(tmp_path, db, sim_recipe) as url:
            # every page says who holds the station: run, operator, where from, since when
            for path in ("/", "/runs", "/dashboard", "/trends", "/plan", f"/runs/{run_id}"):
                page.goto(url + path)
                held = page.wait_for_selector('#station-status [data-station="sim-01"]'
                                              '[data-held="yes"]')
                text = " ".join(held.inner_text().split())
                assert f"station sim-01 is in use by run {run_id} (operator kim" in text, \
                    (path, text)
                assert "from calstation run" in text and "since 20" in text, (path, text)
            # the operator page: Start is disabled before it is pressed, with the reason
            page.goto(url + "/")
            page.select_option("#recipe", sim_recipe.name)
            page.fill("#operator", "ann")
            assert page.is_disabled("#start-button")
            reason = page.inner_text("#start-blocked")
            assert "Start is unavailable: station sim-01 is in use" in reason, reason
            assert "operator kim" in reason and "wait for that run to end" in reason.lower()
            assert page.locator("#run:not([hidden])").count() == 0
            assert _runs(db) == 1
            assert terminal.poll() is None  # the terminal's run goes on, at its prompt
            # the terminal run ends: the open page offers Start again by itself
            terminal.stdin.write("abort\n")  # type: ignore[union-attr]
            terminal.stdin.flush()  # type: ignore[union-attr]
            page.wait_for_selector('#station-status [data-station="sim-01"][data-held="no"]',
                                   timeout=60_000)
            page.wait_for_selector("#start-button:not([disabled])")
            assert page.is_hidden("#start-blocked")
    finally:
        if terminal.poll() is None:
            terminal.stdin.write("abort\n")  # type: ignore[union-attr]
            terminal.stdin.flush()  # type: ignore[union-attr]
        out, err = terminal.communicate(timeout=HANG_S)
    assert terminal.returncode == 3, out + err
    with db.session() as s:
        only = s.scalars(select(Run)).one()
        assert only.operator == "kim" and only.status == "aborted"
    assert station_holder(db, "sim-01") is None
