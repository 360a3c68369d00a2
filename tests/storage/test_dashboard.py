"""The QA dashboard over a seeded history: yields, the failure Pareto, control charts that flag
a seeded drift, station against station, the links to the runs, and bad filters."""

from __future__ import annotations

import datetime as dt
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from calstation.storage.dashboard import failure_reason, period_of
from calstation.storage.db import Database, open_database
from calstation.testing.qa_history import History

pytest.importorskip("calstation_sim")
from calstation.testing.qa_history import Drift, seed_history
from calstation.web.app import create_app

END = dt.datetime(2026, 11, 20, 23, 0, tzinfo=dt.UTC)


@pytest.fixture(scope="module")
def seeded(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Database, History, Path]]:
    tmp = tmp_path_factory.mktemp("dashboard")
    db = open_database(f"sqlite:///{tmp / 'qa.db'}")
    history = seed_history(db, ["bench-a", "bench-b"], 28, 12, end=END,
                           drift=Drift("bench-b", "tz", per_day=0.0004, start_day=21))
    yield db, history, tmp
    db.dispose()


@pytest.fixture(scope="module")
def client(seeded: tuple[Database, History, Path]) -> TestClient:
    db, _, tmp = seeded
    app = create_app(db, data_dir=tmp, recipes_dir=tmp / "recipes")
    return TestClient(app, base_url="http://127.0.0.1")


def get(client: TestClient, url: str) -> Any:
    r = client.get(url)
    assert r.status_code == 200, r.text
    return r.json()


def test_yields_count_every_run_of_the_period(client: TestClient,
                                              seeded: tuple[Database, History, Path]) -> None:
    d = get(client, "/dashboard.json?until=2026-11-20&days=28&group=week")
    totals = {y["station"]: y for y in d["yields"] if y["period"] == "all"}
    history = seeded[1]
    assert {s: t["runs"] for s, t in totals.items()} == {
        s: len(ids) for s, ids in history.runs.items()}
    for t in totals.values():
        assert 0.8 < t["yield"] < 1.0
        assert t["first_pass_yield"] < t["yield"]  # some runs repeat a step
        assert 200 < t["median_cycle_s"] < 400
    weeks = [y for y in d["yields"] if y["period"] != "all" and y["station"] == "bench-a"]
    assert sum(w["runs"] for w in weeks) == totals["bench-a"]["runs"]
    assert all(re.fullmatch(r"2026-W\d\d", w["period"]) for w in weeks)


def test_the_pareto_files_failures_by_step_and_limit(client: TestClient) -> None:
    d = get(client, "/dashboard.json?until=2026-11-20&days=28")
    reasons = [p["reason"] for p in d["pareto"]]
    assert {"cube_scan: cube edge error (face fit)", "cube_scan: cube face flatness",
            "fine_tune: σ above calibration.max_sigma"} <= set(reasons)
    counts = [p["count"] for p in d["pareto"]]
    assert counts == sorted(counts, reverse=True)
    assert d["pareto"][-1]["cumulative"] == pytest.approx(1.0)


def test_control_charts_flag_the_seeded_drift_and_few_others(
        client: TestClient, seeded: tuple[Database, History, Path]) -> None:
    d = get(client, "/dashboard.json?until=2026-11-20&days=28&station=bench-b"
                    "&param=tz&param=ry&param=edge_error")
    assert [c["param"] for c in d["charts"]] == ["tz", "ry", "edge_error"]
    tz = d["charts"][0]
    drifting = set(seeded[1].drifting)
    late = [p for p in tz["points"] if p["run"] in drifting]
    assert late and sum(1 for p in late if p["rules"]) > 0.7 * len(late)
    early = [p for p in tz["points"] if p["run"] not in drifting]
    assert sum(1 for p in early if p["rules"]) < 0.1 * len(early)
    lim = tz["limits"]
    assert tz["unit"] == "m" and d["charts"][1]["unit"] == "rad"  # as stored, and said so
    assert lim["upper"] == pytest.approx(lim["centre"] + 3 * lim["sigma"])
    assert 0.05e-3 < lim["sigma"] < 0.3e-3  # m: the calibration's scatter, not the drift
    assert lim["limit"] == pytest.approx(2.0e-3)  # the recipe's drift limit, m
    assert d["charts"][2]["limits"]["limit"] == pytest.approx(1.0e-3)  # the cube's limit, m
    compare = {row["param"]: row for row in d["comparison"]}
    flagged = {s["station"]: s["flagged"] for s in compare["tz"]["stations"]}
    assert flagged["bench-b"] > 5 * max(1, flagged["bench-a"])


def test_the_page_draws_every_chart_with_links_to_runs(client: TestClient) -> None:
    r = client.get("/dashboard?until=2026-11-20&days=28&station=bench-b&param=tz&param=twist_deg")
    assert r.status_code == 200
    html = r.text
    for fig in ("yield", "cycle", "pareto", "chart-tz", "chart-twist_deg", "compare"):
        assert f'data-figure="{fig}"' in html
    assert "cube side-face twist (°)" in html and "tz — translation along z (mm)" in html
    assert re.search(r'"customdata": \["/runs/\d+"', html)  # a chart's points
    assert "/runs?status=failed&amp;failed_step=cube_scan" in html  # the Pareto's table
    assert '<a href="/dashboard">dashboard</a>' in html


@pytest.mark.parametrize(("query", "message"), [
    ("param=edge", "param: 'edge' is not one of"),
    ("until=yesterday", "until: 'yesterday' is not a date"),
    ("station=nowhere", "station: 'nowhere' has no run"),
])
def test_bad_filters_are_named(client: TestClient, query: str, message: str) -> None:
    r = client.get(f"/dashboard.json?{query}")
    assert r.status_code == 400 and message in r.json()["error"]
    assert client.get(f"/dashboard?{query}").status_code == 400


def test_an_empty_database_gives_an_empty_dashboard(tmp_path: Path) -> None:
    db = open_database(f"sqlite:///{tmp_path / 'empty.db'}")
    c = TestClient(create_app(db, data_dir=tmp_path, recipes_dir=tmp_path),
                   base_url="http://127.0.0.1")
    d = get(c, "/dashboard.json")
    assert d["yields"] == [] and d["pareto"] == [] and d["charts"] == []
    assert "No run in this period" in c.get("/dashboard").text
    db.dispose()


def test_the_favicon_is_served(client: TestClient) -> None:
    r = client.get("/favicon.ico")
    assert r.status_code == 200 and r.headers["content-type"].startswith("image/svg+xml")
    assert r.text.startswith("<svg")
    assert 'rel="icon" href="/favicon.ico"' in client.get("/runs").text


def test_failure_reasons_and_periods() -> None:
    assert failure_reason("cube_scan", "QA cube check failed: perpendicularity 0.6° > 0.5°") \
        == ("cube_scan", "cube perpendicularity")
    # a hole in the scan is the cause of the faces it hides: filed as the lines lost
    assert failure_reason("cube_scan", "cube check failed: the scan's lines leave a hole of 40° "
                          "in the platter's turn (from 30° to 70°): lines were lost between the "
                          "lidar and the station …; faces 1+ have too few returns for a plane "
                          "fit …") == ("cube_scan", "lidar lines lost")
    assert failure_reason("preflight", "lidar: no answer") == ("preflight", "lidar")
    assert failure_reason(None, None) == ("run", "no message")
    t = dt.datetime(2026, 11, 19, 10, tzinfo=dt.UTC)  # a Thursday
    assert period_of(t, "week") == ("2026-W47", dt.date(2026, 11, 16), dt.date(2026, 11, 22))
    assert period_of(t, "day")[0] == "2026-11-19"
