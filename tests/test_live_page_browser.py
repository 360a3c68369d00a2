"""The operator's and the QA engineer's pages in a real browser: one duration formatter in the
pages and on the server, the station's status on every page, no page breaking its
Content-Security-Policy, the placement drawings' legends fitting their pictures.

Run with ``pytest -m browser`` (``make test`` does).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from test_web_browser import db, page  # noqa: F401  (the fixtures)
from webstation import CHROMIUM, copy_recipe, served

from calstation import display, plugins
from calstation.storage.db import Database
from calstation.web.app import create_app

calstation_sim = pytest.importorskip("calstation_sim")
from calstation_sim import plugin as sim_plugin  # noqa: E402

REPO = Path(__file__).resolve().parents[1]

pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(not Path(CHROMIUM).exists(),
                       reason=f"{CHROMIUM} missing: run scripts/system-deps.sh"),
]


@pytest.fixture
def app(tmp_path: Path, db: Database) -> Iterator[Any]:  # noqa: F811
    recipe = copy_recipe(REPO / "recipes" / "sim-periodicity.yaml", tmp_path / "recipes")
    with plugins.isolated(sim_plugin):
        yield create_app(db, data_dir=tmp_path / "data", recipes_dir=recipe.parent)


def test_the_pages_write_durations_as_the_server_does(app: Any, page: Any) -> None:  # noqa: F811
    samples = [0.0, 0.04, 0.05, 4.25, 9.94, 9.96, 10.4, 10.5, 59.4, 59.6, 61.0, 130.72, 3599.4,
               3600.0, 3725.0, 86_399.0]
    with served(app) as url:
        page.goto(url + "/runs")
        shown = page.evaluate("(xs) => xs.map(window.calstationStatus.duration)", samples)
    assert shown == [display.duration(x) for x in samples]


def test_every_page_shows_who_holds_the_station(
        app: Any, page: Any, db: Database) -> None:  # noqa: F811
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
        app: Any, page: Any, db: Database) -> None:  # noqa: F811
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


@pytest.mark.parametrize("fixture", ["static_target", "spin_target", "qa_cube"])
def test_the_placement_drawings_legend_fits_its_picture(page: Any, fixture: str) -> None:  # noqa: F811
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
