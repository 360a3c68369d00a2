"""The operator page in a real browser, used run after run: a second run shows nothing of the
first, the start form offers only what can run and remembers the operator, the prompt's Abort
asks first, and the run header and the end screen say what an operator needs.

Run with ``pytest -m browser`` (``make test`` does).
"""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from test_station import StationTestPlugin, lean_recipe
from test_web_browser import click_answer, db, place, station, wait_end  # noqa: F401  (fixtures, helpers)
from webstation import CHROMIUM

from calstation import plugins
from calstation.storage.db import Database

calstation_sim = pytest.importorskip("calstation_sim")
from calstation_sim import plugin as sim_plugin  # noqa: E402

REPO = Path(__file__).resolve().parents[1]

pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(not Path(CHROMIUM).exists(),
                       reason=f"{CHROMIUM} missing: run scripts/system-deps.sh"),
]


@pytest.fixture
def station_plugin() -> Iterator[StationTestPlugin]:
    plugin = StationTestPlugin()
    with plugins.isolated(sim_plugin, plugin):
        yield plugin


@pytest.fixture
def dialogs(browser: Any) -> Iterator[tuple[Any, list[str]]]:
    """A page whose confirmation dialogs are refused while ``answers[0] == "dismiss"``, else
    accepted; the dialogs' messages are collected."""
    context = browser.new_context(viewport={"width": 1200, "height": 860})
    pg = context.new_page()
    pg.set_default_timeout(90_000)
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
    tmp_path: Path, db: Database, dialogs: tuple[Any, list[str]],  # noqa: F811
    station_plugin: StationTestPlugin,
) -> None:
    page, seen = dialogs
    recipes = tmp_path / "recipes"
    recipes.mkdir()
    recipe = lean_recipe(recipes)
    shutil.copy(REPO / "recipes" / "real-station-template.yaml", recipes)
    with station(tmp_path, db, recipe) as url:
        page.goto(url + "/")
        # the start form: the template is listed but cannot be chosen; no operator yet
        options = page.locator("#recipe option")
        assert page.locator("#recipe option:not([disabled])").all_inner_texts() == ["lean.yaml"]
        template = page.locator('#recipe option[value="real-station-template.yaml"]')
        assert template.is_disabled() and "cannot run: it is a template" in template.inner_text()
        assert options.count() == 2 and page.input_value("#operator") == ""
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
