"""The operator's and the QA engineer's pages in a real browser: live clocks that count from the
server's time, one duration formatter in the pages and on the server, the station's status on
every page, a hidden page drawing nothing, no page breaking its Content-Security-Policy, the
placement drawings' legends fitting their pictures.

Run with ``pytest -m browser`` (``make test`` does).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from calstation import display, plugins
from calstation.storage.db import Database
from calstation.web.app import create_app
from tests.support.webstation import CHROMIUM, copy_recipe, served

calstation_sim = pytest.importorskip("calstation_sim")
from calstation_sim import plugin as sim_plugin  # noqa: E402

REPO = Path(__file__).resolve().parents[2]

pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(not Path(CHROMIUM).exists(),
                       reason=f"{CHROMIUM} missing: run scripts/system-deps.sh"),
]


@pytest.fixture
def app(tmp_path: Path, db: Database) -> Iterator[Any]:
    recipe = copy_recipe(REPO / "recipes" / "sim-periodicity.yaml", tmp_path / "recipes")
    with plugins.isolated(sim_plugin):
        yield create_app(db, data_dir=tmp_path / "data", recipes_dir=recipe.parent)


def test_a_page_opened_long_after_the_state_last_changed_counts_from_the_servers_clock(
        app: Any, page: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    live = app.state.runner.live
    live.begin(7, "sim-periodicity", "ann", None, station="sim-01")
    live.update(lambda st: setattr(st, "started_at", time.time() - 600.0))
    app.state.status.current()  # the station's holders read: no change to come from them
    # the state last changed a minute ago (a run waiting at a prompt): the event stream's
    # message was made then, and is sent as it was to every page opened since
    real = time.time
    monkeypatch.setattr("calstation.web.live.time.time", lambda: real() - 60.0)
    app.state.hub.message()
    monkeypatch.setattr("calstation.web.live.time.time", real)
    with served(app) as url:
        page.goto(url + "/")
        page.wait_for_function("() => document.getElementById('app')"
                               f".getAttribute('data-streamed') === '{live.version}'")
        # the stream's state has been rendered; the elapsed time is the server's: 10 min
        page.wait_for_timeout(1200)  # a tick of the page's clock
        assert page.inner_text("#run-elapsed").startswith("10 min"), \
            page.inner_text("#run-elapsed")


def test_the_pages_write_durations_as_the_server_does(app: Any, page: Any) -> None:
    samples = [0.0, 0.04, 0.05, 4.25, 9.94, 9.96, 10.4, 10.5, 59.4, 59.6, 61.0, 130.72, 3599.4,
               3600.0, 3725.0, 86_399.0]
    with served(app) as url:
        page.goto(url + "/runs")
        shown = page.evaluate("(xs) => xs.map(window.calstationStatus.duration)", samples)
    assert shown == [display.duration(x) for x in samples]


def test_every_page_shows_who_holds_the_station(
        app: Any, page: Any, db: Database) -> None:
    from calstation.station.lock import Holder, take_station

    with served(app) as url:
        page.goto(url + "/runs")
        free = page.wait_for_selector('#station-status [data-station="sim-01"]')
        assert free.get_attribute("data-held") == "no"
        assert "station sim-01 is free" in free.inner_text()
        holder = Holder.here("kim", "calstation run in terminal /dev/pts/7")
        hold = take_station(db, "sim-01", holder)
        try:
            # an open page follows by itself
            held = page.wait_for_selector(
                '#station-status [data-station="sim-01"][data-held="yes"]', timeout=30_000)
            text = " ".join(held.inner_text().split())
            assert "station sim-01 is in use by a run starting (operator kim) from calstation " \
                   "run in terminal /dev/pts/7" in text and "since 20" in text, text
            page.goto(url + "/")
            assert page.is_disabled("#start-button")
            assert "Start is unavailable: station sim-01 is in use" in page.inner_text(
                "#start-blocked")
        finally:
            hold.release()
        page.wait_for_selector("#start-button:not([disabled])", timeout=30_000)


def test_no_page_breaks_its_content_security_policy(
        app: Any, page: Any, db: Database) -> None:
    from calstation.testing.qa_history import seed_history

    seed_history(db, ["sim-01"], 3, 4, seed=5)
    page.add_init_script(
        "window.__csp = []; document.addEventListener('securitypolicyviolation', "
        "e => window.__csp.push(e.violatedDirective + ' ' + e.sample));")
    with served(app) as url:
        for path in ("/", "/dashboard", "/trends?param=tx&param=ry", "/runs", "/plan",
                     "/runs/1", "/compare?a=1&b=2"):
            page.goto(url + path)
            page.wait_for_load_state("load")
            page.wait_for_timeout(500)
            assert page.evaluate("window.__csp") == [], path


def _long_spin_recipe(folder: Path) -> Path:
    """The simulated recipe with a spin scan of 4 turns, whatever the budget says (time to
    look at the page while the platter turns)."""
    import yaml

    data = yaml.safe_load((REPO / "recipes" / "sim-periodicity.yaml").read_text())
    data["steps"]["spin_scan"].update(revolutions=4.0, max_revolutions=4.0, rpm=10)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "sim-long-spin.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


DRAWS = """() => ["line-plot", "cloud-plot"].reduce(
  (n, id) => n + Number(document.getElementById(id).getAttribute("data-draws") || 0), 0)"""


SET_HIDDEN = """(hidden) => {
  Object.defineProperty(document, "hidden", {configurable: true, get: () => hidden});
  Object.defineProperty(document, "visibilityState", {configurable: true,
                        get: () => hidden ? "hidden" : "visible"});
  document.dispatchEvent(new Event("visibilitychange"));
}"""


def test_a_hidden_page_draws_nothing_and_catches_up_when_shown(
        tmp_path: Path, db: Database, page: Any) -> None:
    from tests.support.webpage import click_answer, place, start

    recipe = _long_spin_recipe(tmp_path / "recipes")
    with plugins.isolated(sim_plugin):
        app = create_app(db, data_dir=tmp_path / "data", recipes_dir=recipe.parent)
        with served(app) as url:
            start(page, url, recipe.name)
            place(page, "static_target")
            click_answer(page, "continue")
            place(page, "spin_target")
            click_answer(page, "continue")
            page.wait_for_selector('#steps li.running[data-step="spin_scan"]')
            page.wait_for_selector("#cloud-plot[data-points]", timeout=120_000)
            # the cloud: a picture with its title above it, nothing over it, no WebGL
            assert page.locator("#cloud-plot canvas").count() == 1
            assert "reconstructed under" in page.inner_text("#cloud-plot .cloud-title")
            page.evaluate(SET_HIDDEN, True)
            drawn = page.evaluate(DRAWS)
            seen = int(page.get_attribute("#app", "data-streamed") or 0)
            # the run goes on and its states keep coming: five more, drawn by nobody
            page.wait_for_function(
                f"() => Number(document.getElementById('app').getAttribute('data-streamed')) >= "
                f"{seen + 5}", timeout=60_000)
            assert page.evaluate(DRAWS) == drawn
            assert page.get_attribute('#steps li[data-step="spin_scan"]', "class") \
                .startswith("running")
            page.evaluate(SET_HIDDEN, False)
            page.wait_for_function(f"() => ({DRAWS})() > {drawn}", timeout=30_000)
            page.click("#abort-button")
            page.wait_for_selector("#verdict")


@pytest.mark.parametrize("fixture", ["static_target", "spin_target", "qa_cube"])
def test_the_placement_drawings_legend_fits_its_picture(page: Any, fixture: str) -> None:
    from calstation.recipes import load_recipe
    from calstation.web.placement import placement_svg

    recipe = load_recipe(REPO / "recipes" / "sim-periodicity.yaml").recipe
    svg = placement_svg(recipe.fixtures.platter.radius, getattr(recipe.fixtures, fixture),
                        f"place the {fixture}")
    page.set_content(f"<!doctype html><body style='margin:0'><div style='width:360px'>{svg}"
                     "</div></body>")
    width = page.evaluate("() => document.querySelector('svg').viewBox.baseVal.width")
    ends = page.evaluate("() => [...document.querySelectorAll('text.legend')].map("
                         "t => t.getBBox().x + t.getBBox().width)")
    assert ends and max(ends) <= width, (ends, width)
    legend = " ".join(page.evaluate(
        "() => [...document.querySelectorAll('text.legend')].map(t => t.textContent)"))
    if fixture == "qa_cube":  # the drawing and the prompt say the same: where, how turned
        assert "94 mm from the axis" in legend and "z +50 mm" in legend, legend
        assert "turned 20°" in legend, legend
