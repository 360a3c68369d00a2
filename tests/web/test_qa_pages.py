"""The QA pages' defects, each fixed: several trends at once with readable names (cube
perpendicularity and twist offered), the serial filter by part, compare with the serials,
404 for a run that does not exist, one navigation bar with export links on /runs/N, times for
people, exports of a calibration that was not accepted marked so."""

from __future__ import annotations

import datetime as dt
import re
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from calstation.storage.db import Calibration, Database, Run, open_database
from calstation.storage.templating import when

pytest.importorskip("calstation_sim")
from calstation.testing.qa_history import seed_history
from calstation.web.app import create_app

END = dt.datetime(2026, 11, 20, 22, 0, tzinfo=dt.UTC)


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[TestClient, Database]]:
    tmp = tmp_path_factory.mktemp("qa-pages")
    db = open_database(f"sqlite:///{tmp / 'qa.db'}")
    seed_history(db, ["bench-a", "bench-b"], 6, 10, end=END, seed=3)
    yield TestClient(create_app(db, data_dir=tmp, recipes_dir=tmp / "recipes"),
                     base_url="http://127.0.0.1"), db
    db.dispose()


def test_trends_show_several_parameters_with_their_names(
        client: tuple[TestClient, Database]) -> None:
    c, _ = client
    r = c.get("/trends?station=bench-a&param=tz&param=perpendicularity_deg&param=twist_deg")
    assert r.status_code == 200
    html = r.text
    for name in ("tz — translation along z (mm)", "cube perpendicularity (°)",
                 "cube side-face twist (°)"):
        assert "<h2" in html and name in html
    assert html.count("data-figure=\"trend-") == 3
    assert "edge_error" not in re.sub(r'(value|name|data-\w+|id)="[^"]*"', "", html.split(
        "<main>")[1].split("<script")[0]).replace("param=edge_error", "")
    j = c.get("/trends.json?station=bench-a&param=tz&param=twist_deg").json()
    assert [t["param"] for t in j["trends"]] == ["tz", "twist_deg"] and j["param"] == "tz"
    twist = j["trends"][1]["points"]
    assert twist and all(p["limit"] == pytest.approx(0.1) for p in twist)
    assert c.get("/trends.json?param=tz&param=bogus").status_code == 400


def test_the_serial_filter_takes_part_of_a_serial(client: tuple[TestClient, Database]) -> None:
    c, db = client
    with db.session() as s:
        serial = s.scalars(select(Run.unit_serial).order_by(Run.id).limit(1)).one()
    assert serial is not None
    part = serial[-5:].lower()
    runs = c.get("/runs.json", params={"serial": part}).json()["runs"]
    assert runs and all(part in r["serial"].lower() for r in runs)
    assert serial in {r["serial"] for r in runs}
    assert c.get("/runs.json", params={"serial": "%"}).json()["runs"] == []


def test_failed_step_and_reason_filters(client: tuple[TestClient, Database]) -> None:
    c, _ = client
    runs = c.get("/runs.json", params={"failed_step": "cube_scan",
                                       "reason": "cube edge error (face fit)"}).json()["runs"]
    assert runs and all(r["status"] == "failed" for r in runs)
    assert all(r["cube_check"]["edge_error"] > 0.001 for r in runs)


def test_compare_shows_the_serials(client: tuple[TestClient, Database]) -> None:
    c, db = client
    with db.session() as s:
        a, b = s.scalars(select(Run.id).where(Run.status == "passed").limit(2)).all()
        serials = [s.get(Run, i).unit_serial for i in (a, b)]  # type: ignore[union-attr]
    html = c.get(f"/compare?a={a}&b={b}").text
    row = re.search(r"<tr><td>unit serial</td>(.*?)</tr>", html)
    assert row and serials[0] in row.group(1) and serials[1] in row.group(1)
    assert "different units" in row.group(1)
    assert "tx — translation along x (mm)" in html


@pytest.mark.parametrize("path", ["/runs/99999", "/runs/99999.json",
                                  "/runs/99999/report.html", "/runs/99999/export.yaml",
                                  "/runs/99999/views.json"])
def test_a_run_that_does_not_exist_is_404(client: tuple[TestClient, Database],
                                          path: str) -> None:
    r = client[0].get(path)
    assert r.status_code == 404 and "no run 99999" in r.text


def test_the_run_page_has_the_stations_bar_and_exports(
        client: tuple[TestClient, Database]) -> None:
    c, db = client
    with db.session() as s:
        run_id = s.scalars(select(Run.id).where(Run.status == "passed").limit(1)).one()
    html = c.get(f"/runs/{run_id}").text
    bar = re.search(r'<nav class="top">.*?</nav>', html, re.S)
    assert bar and all(f'href="{p}"' in bar.group(0) for p in (
        "/", "/dashboard", "/runs", "/trends", "/campaigns", "/plan"))
    assert f'href="/runs/{run_id}.json"' in bar.group(0)
    for fmt in ("yaml", "json", "urdf", "csv"):
        assert f'href="/runs/{run_id}/export.{fmt}"' in html
    assert 'rel="icon"' in html
    # times for people: no ISO "T", no microseconds
    started = re.search(r"<dt>started</dt><dd>([^<]+)</dd>", html)
    assert started and re.fullmatch(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d UTC", started.group(1))


def test_times_are_for_people_on_every_page(client: tuple[TestClient, Database]) -> None:
    c, _ = client
    for path in ("/runs", "/trends?station=bench-a&param=tx", "/dashboard?until=2026-11-20"):
        html = c.get(path).text
        assert not re.search(r"\d\d:\d\d:\d\d\.\d{3,6}", html), path
        assert not re.search(r">\d{4}-\d\d-\d\dT\d\d:\d\d", html), path
    assert when("2026-11-23T14:05:09.123456+00:00") == "2026-11-23 14:05 UTC"
    assert when("2026-11-23T15:05:09+01:00", seconds=True) == "2026-11-23 14:05:09 UTC"
    assert when(None) == "—" and when("soon") == "soon"


def test_exports_of_a_calibration_not_accepted_are_marked(
        client: tuple[TestClient, Database]) -> None:
    c, db = client
    with db.session() as s:
        run_id = s.scalars(select(Run.id).join(Calibration).where(
            Run.status == "failed", ~Calibration.accepted).limit(1)).one()
        ok_id = s.scalars(select(Run.id).where(Run.status == "passed").limit(1)).one()
    html = c.get("/runs", params={"status": "failed"}).text
    row = re.search(rf'<tr class="failed" data-run="{run_id}">.*?</tr>', html, re.S)
    assert row and "not accepted" in row.group(0)
    r = c.get(f"/runs/{run_id}/export.yaml")
    assert r.status_code == 200
    assert "NOT-ACCEPTED" in r.headers["content-disposition"]
    assert "NOT-ACCEPTED" not in c.get(f"/runs/{ok_id}/export.yaml").headers[
        "content-disposition"]
    page = c.get(f"/runs/{run_id}").text
    assert 'id="partial"' in page and "NOT accepted" in page
    assert re.search(r'id="exports".*?not accepted', page, re.S)


def test_the_report_of_a_run_without_recordings_says_so(tmp_path: Path) -> None:
    from calstation.storage.report_html import render_report, report_data

    db = open_database(f"sqlite:///{tmp_path / 'one.db'}")
    seed_history(db, ["solo"], 1, 3, end=END, seed=1)
    data = report_data(db, 1)
    html = render_report(data, plotly_src="../plotly.min.js")
    assert 'id="no-plotly"' in html and "plotly-" in html
    db.dispose()


def test_the_report_says_when_the_cubes_height_was_not_judged(tmp_path: Path) -> None:
    """A cube of another finish than the platter: its height, measured from the platter, is
    left out of the edge error, and the report says so beside the face-fit edges."""
    from calstation.storage.db import CubeCheckRecord
    from calstation.storage.report_html import render_report, report_data

    db = open_database(f"sqlite:///{tmp_path / 'one.db'}")
    seed_history(db, ["solo"], 1, 3, end=END, seed=1)
    note = "the edge error leaves it out"
    assert note not in render_report(report_data(db, 1), plotly_src="../plotly.min.js")
    with db.session() as s:
        for check in s.scalars(select(CubeCheckRecord).where(CubeCheckRecord.run_id == 1)):
            check.height_judged = False
    assert note in render_report(report_data(db, 1), plotly_src="../plotly.min.js")
    db.dispose()
