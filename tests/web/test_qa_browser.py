"""The QA pages and the run report in a real browser (Debian's chromium, Playwright): the
dashboard over weeks of seeded history with out-of-control points, the run page's first paint,
and the report printed to PDF.

Run with ``pytest -m browser``. With ``CALSTATION_DOCS_SCREENSHOTS=1`` the tests also write the
pictures of ``docs/station.md`` (``docs/station/*.png``).
"""

from __future__ import annotations

import datetime as dt
import os
import re
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from calstation.storage.db import Database, Run, open_database
from calstation.web.app import create_app
from tests.support.webstation import CHROMIUM, HANG_S, served, shot as docs_shot

playwright_api = pytest.importorskip("playwright.sync_api")
pytest.importorskip("calstation_sim")

REPO = Path(__file__).resolve().parents[2]
REPORT_MAX_BYTES = 1_500_000
DOCS_SHOTS = os.environ.get("CALSTATION_DOCS_SCREENSHOTS") == "1"

pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(not Path(CHROMIUM).exists(),
                       reason=f"{CHROMIUM} missing: run scripts/system-deps.sh"),
]


@pytest.fixture
def page(browser: Any) -> Iterator[Any]:
    context = browser.new_context(viewport={"width": 1250, "height": 900})
    pg = context.new_page()
    pg.set_default_timeout(HANG_S * 1000)  # a hang guard: waits end at their event
    yield pg
    context.close()


def shot(page: Any, name: str, full: bool = False) -> None:
    """A picture for docs/station.md: 64 colours, at most 1250 pixels wide (the QA pages are
    wide)."""
    docs_shot(page, name, full, colours=64, max_width=1250)


@pytest.fixture(scope="module")
def history(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Database, Any, Path]]:
    from calstation.testing.qa_history import Drift, seed_history

    tmp = tmp_path_factory.mktemp("qa-history")
    db = open_database(f"sqlite:///{tmp / 'qa.db'}")
    end = dt.datetime.now(dt.UTC).replace(microsecond=0)
    seeded = seed_history(db, ["line-1", "line-2", "line-3"], 42, 16, end=end,
                          drift=Drift("line-2", "tz", per_day=0.0003, start_day=32))
    yield db, seeded, tmp
    db.dispose()


def test_the_dashboard_shows_weeks_of_stations_and_flags_the_drift(
        history: tuple[Database, Any, Path], page: Any) -> None:
    db, seeded, tmp = history
    app = create_app(db, data_dir=tmp, recipes_dir=tmp / "recipes")
    with served(app) as url:
        t0 = time.perf_counter()
        page.goto(url + "/dashboard?station=line-2&days=42&param=tz&param=ry&param=edge_error")
        page.wait_for_selector("body[data-figures-drawn]")
        print(f"dashboard: every figure drawn {time.perf_counter() - t0:.2f} s after the request")
        assert page.locator("#yields tr[data-station]").count() == 3
        assert page.locator(".dash-figure[data-drawn]").count() == page.locator(
            ".dash-figure").count() == 7
        tz = page.locator('#charts tr[data-param="tz"]')
        assert "flagged" in (tz.get_attribute("class") or "")
        flagged = int(tz.locator("td").last.inner_text())
        drifting = len(seeded.drifting)
        assert flagged > 0.5 * drifting
        ry = int(page.locator('#charts tr[data-param="ry"] td').last.inner_text())
        assert ry < flagged / 4
        assert page.locator("#pareto tr").count() > 3
        shot(page, "dashboard", full=True)
        # a flagged run is one click away, from its list and from its point on the chart
        listed = [int(t) for t in page.locator('.flagged-runs[data-param="tz"] a')
                  .all_inner_texts()]
        run_id = next(r for r in listed if r in seeded.drifting)
        page.evaluate("""id => document.getElementById('fig-chart-tz').emit('plotly_click',
            {points: [{customdata: '/runs/' + id}]})""", run_id)
        page.wait_for_url(re.compile(rf"/runs/{run_id}$"))
        assert page.locator("nav.top a[href='/dashboard']").count() == 1
        # the Pareto's bars lead to the runs that failed so
        page.go_back()
        page.wait_for_selector("body[data-figures-drawn]")
        page.locator("#pareto a").first.click()
        page.wait_for_selector("#history")
        rows = page.locator("#history tr[data-run]")
        assert rows.count() > 0
        assert all(s == "failed" for s in rows.locator("td.status-cell").all_inner_texts())
        if DOCS_SHOTS:
            _other_pages(page, url, seeded)


def _other_pages(page: Any, url: str, seeded: Any) -> None:
    """Pictures of the other QA pages for docs/station.md, over the seeded history."""
    page.goto(url + "/runs?station=line-2&limit=25")
    shot(page, "history")
    page.goto(url + "/trends?station=line-2&param=tz&param=ry&param=twist_deg")
    page.wait_for_selector("body[data-figures-drawn]")
    shot(page, "trends", full=True)
    a, b = seeded.runs["line-2"][3], seeded.drifting[-1]
    page.goto(url + f"/compare?a={a}&b={b}")
    shot(page, "compare", full=True)
    for name in ("campaigns", "plan", "login"):
        page.goto(url + f"/{name}")
        shot(page, name)


@pytest.fixture(scope="module")
def default_run(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Database, int, Path]]:
    """One unattended run of the default simulated recipe (``recipes/sim-periodicity.yaml``)."""
    from calstation_sim import plugin as sim_plugin

    from calstation import plugins
    from calstation.cli._operator import ConsoleOperator
    from calstation.recipes import load_recipe
    from calstation.station.runs import start_run

    tmp = tmp_path_factory.mktemp("default-run")
    db = open_database(f"sqlite:///{tmp / 'station.db'}")
    with plugins.isolated(sim_plugin):
        run_id, _ = start_run(load_recipe(REPO / "recipes" / "sim-periodicity.yaml"), db,
                              ConsoleOperator(unattended=True), operator="ann",
                              data_dir=tmp / "data")
    yield db, run_id, tmp
    db.dispose()


def test_the_default_runs_report_is_small_and_prints_every_figure(
        default_run: tuple[Database, int, Path], browser: Any) -> None:
    from calstation.station.runs import run_folder

    db, run_id, _ = default_run
    report = run_folder(db, run_id) / "report.html"
    size = report.stat().st_size
    print(f"report.html of the default run: {size / 1e6:.2f} MB")
    assert size <= REPORT_MAX_BYTES
    html = report.read_text()
    assert 'data-figure="cost"' in html  # drawn under the accepted periodicity+cube
    context = browser.new_context(offline=True, viewport={"width": 1100, "height": 900})
    rp = context.new_page()
    rp.goto(report.as_uri())
    rp.wait_for_selector("body[data-report-ready]")
    t0 = time.perf_counter()
    rp.wait_for_selector("body[data-print-ready]")
    print(f"pictures for print ready {time.perf_counter() - t0:.1f} s after the figures")
    figures = rp.locator("[data-figure]").count()
    assert figures >= 4  # two 3D views, residuals, cost
    assert rp.locator("img.print-image").count() == figures
    rp.emulate_media(media="print")
    # on paper: a picture in place of each figure, each smaller than a page
    page_px = (297 - 30) / 25.4 * 96
    for img in rp.locator("img.print-image").all():
        box = img.bounding_box()
        assert box is not None and 50 < box["height"] < page_px
    assert rp.locator(".plot-container:visible").count() == 0
    pdf = rp.pdf(format="A4", print_background=True)
    context.close()
    images = len(re.findall(rb"/Subtype\s*/Image", pdf))
    print(f"report PDF: {len(pdf) / 1e6:.2f} MB, {images} images for {figures} figures")
    assert images >= figures


def test_the_report_prints_as_a_certificate(
        default_run: tuple[Database, int, Path], browser: Any) -> None:
    """On paper every page names the station, the run, the unit and the result and counts the
    pages; no number breaks across lines; no figure takes a page of its own."""
    import io

    pypdf = pytest.importorskip("pypdf")
    from calstation.station.runs import run_folder

    db, run_id, _ = default_run
    report = run_folder(db, run_id) / "report.html"
    with db.session() as s:
        run = s.get(Run, run_id)
        assert run is not None
        station, status = run.station.name, run.status
    from calstation.storage.report_html import report_data

    serial = report_data(db, run_id, views=False)["serial"]
    verdict = {"passed": "PASS", "failed": "FAIL"}.get(status, status.upper())
    context = browser.new_context(offline=True, viewport={"width": 1100, "height": 900})
    rp = context.new_page()
    rp.goto(report.as_uri())
    rp.wait_for_selector("body[data-print-ready]", timeout=180_000)
    rp.emulate_media(media="print")
    # figures sized to the page: each at most a third of an A4 page's height
    for img in rp.locator("img.print-image").all():
        box = img.bounding_box()
        assert box is not None and box["height"] <= 86 / 25.4 * 96 + 1
    pdf = rp.pdf(format="A4", print_background=True, prefer_css_page_size=True)
    context.close()
    pages = [page.extract_text() or "" for page in pypdf.PdfReader(io.BytesIO(pdf)).pages]
    assert len(pages) >= 2
    for i, text in enumerate(pages, start=1):
        flat = " ".join(text.split())
        assert f"station {station}" in flat, (i, flat[:300])
        assert f"run {run_id} · unit {serial} · {verdict}" in flat, (i, flat[:300])
        assert f"page {i} of {len(pages)}" in flat, (i, flat[-300:])
        # no number broken: no exponent, no ± or minus (calstation writes U+2212) at a line's
        # end, no exponent's sign (a path may break at its hyphens)
        assert not re.search(r"\d\.\d+e[-+]?\d", flat), (i, flat)
        for line in text.splitlines():
            end = line.rstrip()
            assert not end.endswith(("±", "−")) or line.strip() in ("±", "−"), (i, line)
            assert not re.search(r"\de-$", end), (i, line)


def test_the_run_page_paints_at_once_and_fetches_its_views(
        default_run: tuple[Database, int, Path], page: Any) -> None:
    db, run_id, tmp = default_run
    app = create_app(db, data_dir=tmp / "data", recipes_dir=tmp / "recipes")
    with served(app) as url:
        page.goto(url + "/static/plotly.min.js")
        fetched: list[str] = []
        page.on("request", lambda r: fetched.append(r.url))
        response = page.goto(url + f"/runs/{run_id}", wait_until="commit")
        # at once: the verdict is in the page's own HTML, drawn before any script runs, and
        # the reconstructed 3D views are not (their time is benchmarks/run_page.py's)
        html = response.text()
        assert 'id="verdict"' in html and "views.json" in html
        assert len(html) < 400_000, len(html)
        page.wait_for_selector("#verdict")
        assert page.locator("#exports a").count() == 4
        assert page.locator("nav.top a[href='/runs']").count() == 1
        assert "." not in page.inner_text("header dl").split("started")[1].split("\n")[1][-4:]
        page.wait_for_selector("body[data-report-ready]")
        assert page.locator(".view3d[data-drawn]").count() == 2
        assert f"{url}/runs/{run_id}/views.json" in fetched  # fetched after the page
        shot(page, "run", full=True)
    with db.session() as s:
        run = s.get(Run, run_id)
        assert run is not None and run.status in ("passed", "failed")
