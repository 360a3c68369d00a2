"""The web station in a real browser: Debian's chromium driven by Playwright, clicking as an
operator does, against ``calstation serve``'s app served by uvicorn.

Run with ``pytest -m browser`` (``make test`` does, in a second pass). A failing test saves a
screenshot to ``$CALSTATION_TEST_SCREENSHOTS`` (default ``out/browser-failures/``). With
``CALSTATION_DOCS_SCREENSHOTS=1`` the tests also write the pictures of ``docs/station.md`` into
``docs/station/``.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest
import yaml

from calstation import plugins
from calstation.station.runs import run_folder
from calstation.storage.db import Database, Run
from tests.support.station import StationTestPlugin, toy_recipe
from tests.support.webpage import click_answer, place, start, station, wait_end
from tests.support.webstation import (
    CHROMIUM,
    copy_recipe,
    run_status,
    shot,
    steps_of,
)

playwright_api = pytest.importorskip("playwright.sync_api")
calstation_sim = pytest.importorskip("calstation_sim")
from calstation_sim import plugin as sim_plugin  # noqa: E402

REPO = Path(__file__).resolve().parents[2]

pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(not Path(CHROMIUM).exists(),
                       reason=f"{CHROMIUM} missing: run scripts/system-deps.sh"),
]


def classes(page: Any, step: str) -> list[str]:
    """The classes of a step in the page's step list (its status, "current")."""
    value = page.locator(f'#steps li[data-step="{step}"]').get_attribute("class") or ""
    return value.split()


def latest_run(db: Database) -> int:
    with db.session() as s:
        run = s.query(Run).order_by(Run.id.desc()).first()
        assert run is not None
        return run.id


@pytest.mark.slow
def test_a_full_simulated_run_by_clicking_with_a_reload(
    tmp_path: Path, db: Database, page: Any, browser: Any
) -> None:
    recipe = copy_recipe(REPO / "recipes" / "sim-periodicity.yaml", tmp_path / "recipes")
    with plugins.isolated(sim_plugin), station(tmp_path, db, recipe) as url:
        page.goto(url + "/")
        shot(page, "start")
        start(page, url, "sim-periodicity.yaml", serial="LIDAR-0042")
        box = place(page, "static_target")
        assert "L-shaped static target" in box.inner_text()
        assert page.locator("#prompt-svg svg.placement").count() == 1
        shot(page, "placement")
        click_answer(page, "continue")
        place(page, "spin_target")
        # reload mid-run: the same step and the same pending prompt
        page.reload()
        box = place(page, "spin_target")
        assert classes(page, "static_scan") == ["passed"]
        assert "Place the spin target on the platter, its centre 60 mm from the axis" \
            in box.inner_text()
        click_answer(page, "continue")
        # the live lidar line is drawn during the spin scan
        page.wait_for_selector("#line-plot[data-drawn]:not([hidden])")
        assert re.search(r"spin scan", page.inner_text("#line-plot"))
        # with the spin target's expected outline under the initial calibration
        page.wait_for_selector('#line-plot[data-outline="expected"]')
        assert "initial calibration" in page.inner_text("#line-plot")
        shot(page, "scan")
        place(page, "qa_cube")
        click_answer(page, "continue")
        assert wait_end(page) == "PASS"
        run_id = latest_run(db)
        assert run_status(db, run_id) == "passed"
        values = page.inner_text("#result")
        assert "face-fit edge error" in values and "≤ 1.00 mm" in values
        # the run gave the station back: the end screen says so and offers Start at once
        assert page.get_attribute('#station-status [data-station="sim-01"]', "data-held") == "no"
        assert page.is_enabled("#start-button")
        shot(page, "end", full=True)
        # the run folder's report.html opens offline with its 3D views drawn
        report = run_folder(db, run_id) / "report.html"
        offline = browser.new_context(offline=True, viewport={"width": 1200, "height": 860})
        rp = offline.new_page()
        rp.goto(report.as_uri())
        rp.wait_for_selector(".view3d[data-drawn]")
        assert rp.locator(".view3d[data-drawn]").count() == 2
        assert rp.inner_text("#verdict") == "PASS" and "LIDAR-0042" in rp.inner_text("header")
        rp.wait_for_timeout(500)
        shot(rp, "report", full=True)
        offline.close()


def test_a_failed_step_is_retried_from_the_page(
    tmp_path: Path, db: Database, page: Any, station_plugin: StationTestPlugin
) -> None:
    station_plugin.strategy.failures = 1
    (tmp_path / "recipes").mkdir()
    recipe = toy_recipe(tmp_path / "recipes")
    with station(tmp_path, db, recipe) as url:
        start(page, url, "lean.yaml")
        for fixture in ("static_target", "spin_target"):
            place(page, fixture)
            click_answer(page, "continue")
        box = page.wait_for_selector('#prompt:not([hidden])[data-kind="failure"]')
        assert "scripted failure" in page.inner_text("#prompt-error")
        assert page.locator('#prompt button[data-answer="retry"]').is_visible()
        assert "failed" in classes(page, "fine_tune")
        assert "Fine-tuning failed" in box.inner_text()  # in words, not the step's key
        shot(page, "failure")
        click_answer(page, "retry")
        # a fine-tuning is retried from the spin target's placement: re-place, re-scan, re-fit
        place(page, "spin_target")
        click_answer(page, "continue")
        place(page, "qa_cube")
        click_answer(page, "continue")
        wait_end(page)
        run_id = latest_run(db)
        steps = steps_of(db, run_id)
        assert ("fine_tune", 1, "failed") in steps and ("fine_tune", 2, "passed") in steps
        assert run_status(db, run_id) in ("passed", "failed")
        assert page.inner_text('#steps li[data-step="fine_tune"] .attempt').strip() == "(attempt 2)"


def test_abort_during_a_scan_stops_the_motor(
    tmp_path: Path, db: Database, page: Any, station_plugin: StationTestPlugin
) -> None:
    (tmp_path / "recipes").mkdir()
    recipe = toy_recipe(tmp_path / "recipes")
    data = yaml.safe_load(recipe.read_text())
    # a scan far longer than the test (the simulator runs faster than real time): the slowest
    # turn and the longest scan the recipe checks allow
    data["steps"]["spin_scan"].update(rpm=0.5, revolutions=4.9)
    recipe.write_text(yaml.safe_dump(data, sort_keys=False))
    with station(tmp_path, db, recipe) as url:
        start(page, url, "lean.yaml")
        for fixture in ("static_target", "spin_target"):
            place(page, fixture)
            click_answer(page, "continue")
        page.wait_for_selector("#progress:not([hidden])")
        page.wait_for_function(
            "document.querySelector('#progress-text').textContent.includes('spin scan')")
        # closing or reloading the page does not stop the run
        page.reload()
        page.wait_for_selector('#steps li.running[data-step="spin_scan"]')
        motor_before = list(station_plugin.motor_calls)
        page.click("#abort-button")
        assert wait_end(page) == "ABORTED"
        run_id = latest_run(db)
        assert run_status(db, run_id) == "aborted"
        assert steps_of(db, run_id)[-1] == ("spin_scan", 1, "aborted")
        assert station_plugin.motor_calls[len(motor_before):][-2:] == ["emergency_stop", "stop"]
        assert "aborted" in classes(page, "spin_scan")
