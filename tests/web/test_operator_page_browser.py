"""The operator page in a real browser, used run after run: a second run shows nothing of the
first, the start form offers only what can run and remembers the operator, the prompt's Abort
asks first, and the run header and the end screen say what an operator needs.

Run with ``pytest -m browser`` (``make test`` does).
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from calstation.engine.outline import distance_to_outline
from calstation.storage.db import Database
from tests.support.station import StationTestPlugin, toy_recipe
from tests.support.webpage import click_answer, place, station, wait_end
from tests.support.webstation import CHROMIUM, HANG_S, shot, wait_until

calstation_sim = pytest.importorskip("calstation_sim")

REPO = Path(__file__).resolve().parents[2]

pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(not Path(CHROMIUM).exists(),
                       reason=f"{CHROMIUM} missing: run scripts/system-deps.sh"),
]


@pytest.fixture
def dialogs(browser: Any) -> Iterator[tuple[Any, list[str]]]:
    """A page whose confirmation dialogs are refused while ``answers[0] == "dismiss"``, else
    accepted; the dialogs' messages are collected."""
    context = browser.new_context(viewport={"width": 1200, "height": 860})
    pg = context.new_page()
    pg.set_default_timeout(HANG_S * 1000)  # a hang guard: waits end at their event
    answers = ["accept"]
    seen: list[str] = []

    def handle(dialog: Any) -> None:
        seen.append(dialog.message)
        if answers[0] == "dismiss":
            dialog.dismiss()
        else:
            dialog.accept()
    pg.on("dialog", handle)
    pg.answers = answers  # type: ignore[attr-defined]
    yield pg, seen
    context.close()


def _full_run(page: Any) -> str:
    for fixture in ("static_target", "spin_target", "qa_cube"):
        place(page, fixture)
        click_answer(page, "continue")
    return wait_end(page)


def test_a_second_run_shows_nothing_of_the_first(
    tmp_path: Path, db: Database, dialogs: tuple[Any, list[str]],
    station_plugin: StationTestPlugin,
) -> None:
    page, seen = dialogs
    recipes = tmp_path / "recipes"
    recipes.mkdir()
    recipe = toy_recipe(recipes)
    shutil.copy(REPO / "recipes" / "real-station-template.yaml", recipes)
    with station(tmp_path, db, recipe) as url:
        page.goto(url + "/")
        # the start form: the template is listed apart, with its reason, and cannot be
        # chosen; no operator yet
        assert page.locator("#recipe option").all_inner_texts() == ["lean.yaml"]
        assert "real-station-template.yaml: it is a template" in page.text_content("#unrunnable")
        assert page.input_value("#operator") == ""
        page.fill("#operator", "ann")
        page.fill("#serial", "SN-1")
        page.click("#start-button")
        page.wait_for_selector("#run:not([hidden])")
        # the run header: run, unit, operator, recipe and a growing elapsed time
        header = page.inner_text("#run-header")
        assert "SN-1" in header and "ann" in header and "station-test" in header
        page.wait_for_function(
            "document.querySelector('#run-elapsed').textContent.endsWith(' s')")
        # the prompt's Abort asks first: refused, the run goes on at the same prompt
        box = place(page, "static_target")
        assert "L-shaped static target" in box.inner_text()
        page.answers[0] = "dismiss"  # type: ignore[attr-defined]
        click_answer(page, "abort")
        assert seen and "Abort the run?" in seen[-1]
        assert page.locator('#prompt:not([hidden])[data-fixture="static_target"]').count() == 1
        assert page.locator('#prompt button[data-answer="continue"]').is_enabled()
        page.answers[0] = "accept"  # type: ignore[attr-defined]
        click_answer(page, "continue")
        for fixture in ("spin_target", "qa_cube"):
            place(page, fixture)
            click_answer(page, "continue")
        first = wait_end(page)
        assert first in ("PASS", "FAIL")
        end = page.inner_text("#result")
        assert "SN-1" in page.inner_text("#result-unit")
        assert "not estimated" in page.inner_text("#calibration-values")  # rx, the gauge
        assert "fine-tuned" in end and "initial, from the L-target" in end
        times = page.inner_text("#step-times")
        assert "static scan and initial calibration" in times and " s" in times
        assert "fine_tune" not in end and "static_target" not in end
        # the form remembers the operator, and the last run's recipe
        assert page.input_value("#operator") == "ann"
        assert page.input_value("#recipe") == "lean.yaml"
        # a second run: nothing of the first stays while it runs
        page.fill("#serial", "SN-2")
        page.click("#start-button")
        place(page, "static_target")
        assert page.locator("#verdict").count() == 0
        assert page.locator("#result").is_hidden()
        assert page.locator("#report-link").count() == 0
        assert page.locator("#steps li.passed").count() <= 1  # the preflight of this run
        assert "SN-2" in page.inner_text("#run-header")
        log = page.inner_text("#log")
        assert "run 1" not in log
        click_answer(page, "continue")
        for fixture in ("spin_target", "qa_cube"):
            place(page, fixture)
            click_answer(page, "continue")
        assert wait_end(page) in ("PASS", "FAIL")
        assert "SN-2" in page.inner_text("#result-unit")


def _plot(page: Any, selector: str) -> list[dict[str, Any]]:
    """What the page drew in ``selector`` (each set's name and points)."""
    return list(page.evaluate(
        """sel => (document.querySelector(sel).plotted || []).map(t => ({
               name: t.name, x: Array.from(t.x || []), y: Array.from(t.y || [])}))""",
        selector))


def _points(page: Any) -> int:
    """The points the page's 3D cloud holds."""
    return int(page.get_attribute("#cloud-plot", "data-points") or 0)


def _outline(trace: dict[str, Any]) -> list[np.ndarray]:
    """A plotted outline (polylines separated by nulls) as (K, 2) arrays in metres."""
    lines, current = [], []
    for x, y in zip(trace["x"], trace["y"], strict=True):
        if x is None:
            lines.append(np.asarray(current) / 1000.0)
            current = []
        else:
            current.append((x, y))
    return [line for line in lines if len(line) >= 2]


def test_the_live_plots_show_the_expected_outline_and_the_cloud_as_it_grows(
    tmp_path: Path, db: Database, dialogs: tuple[Any, list[str]],
    station_plugin: StationTestPlugin,
) -> None:
    page, _ = dialogs
    (tmp_path / "recipes").mkdir()
    recipe = toy_recipe(tmp_path / "recipes")
    data = yaml.safe_load(recipe.read_text())
    # scans long enough to watch: a static scan of a few seconds, a slow turn
    data["steps"]["static_scan"]["lines"] = 4000
    data["steps"]["spin_scan"].update(rpm=5, revolutions=1.02)
    recipe.write_text(yaml.safe_dump(data, sort_keys=False))
    with station(tmp_path, db, recipe) as url:
        page.goto(url + "/")
        page.fill("#operator", "ann")
        page.click("#start-button")  # no serial given: the lidar's is shown once known
        place(page, "static_target")
        assert page.inner_text("#run-serial") == "sim-0"
        assert page.locator("#result").is_hidden()
        click_answer(page, "continue")
        # before any calibration of this station: the outline under the recipe's nominal
        # mounting, named as such
        page.wait_for_selector('#line-plot[data-outline="expected"]')
        traces = _plot(page, "#line-plot")
        assert [t["name"] for t in traces] == ["returns", "expected outline"]
        assert "nominal mounting" in page.inner_text("#line-plot")
        place(page, "spin_target")
        click_answer(page, "continue")
        # the spin scan: the outline under the initial calibration, and the cloud in 3D
        # (polled from here: the page's policy refuses the evaluated strings of
        # wait_for_function once it has to poll)
        first = wait_until(lambda: _points(page))
        wait_until(lambda: _points(page) > first)
        wait_until(lambda: page.get_attribute("#line-plot", "data-outline") == "expected"
                   and "initial" in page.inner_text("#line-plot"))
        traces = _plot(page, "#line-plot")
        returns = np.column_stack([traces[0]["x"], traces[0]["y"]]) / 1000.0
        outline = _outline(traces[1])
        assert len(outline) >= 2  # the platter and the spin target's pieces
        # the returns on the platter and the target lie on the outline, to the initial
        # calibration's error (ry is not estimated there)
        centre = np.mean(np.vstack(outline), axis=0)
        near = returns[np.hypot(*(returns - centre).T) < 0.25]
        assert near.shape[0] > 50
        d = distance_to_outline(near, outline)
        assert np.median(d) < 0.004, np.median(d)
        assert first < _points(page) <= 6_000  # thinned by the station
        assert page.locator("#cloud-plot canvas").count() == 1
        assert "initial calibration" in page.inner_text("#cloud-plot")
        time.sleep(1.0)  # a few more turns of the cloud for the picture
        shot(page, "live", full=True, octree=True)  # the cloud's yellow kept yellow
        place(page, "qa_cube")
        # the spin scan's cloud is gone at the next placement: no stale view beside the prompt
        wait_until(lambda: page.locator("#cloud-plot").is_hidden(), timeout=30)
        click_answer(page, "continue")
        assert wait_end(page) in ("PASS", "FAIL")
