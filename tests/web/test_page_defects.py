"""The operator's and the QA engineer's pages, each defect a new user found fixed: the start
form, the end screen, the names and times of steps, the failure Pareto, the stations side by
side, the control charts' scale, what a 3D view's residuals mean, the terminal's summary."""

from __future__ import annotations

import datetime as dt
import io
import math
import re
import time
from pathlib import Path

import pytest
import yaml
from fastapi.testclient import TestClient
from sqlalchemy import select

from calstation import display
from calstation.storage.db import Calibration, CubeCheckRecord, Database, Run, Step
from calstation.storage.templating import environment
from calstation.web.app import create_app

REPO = Path(__file__).resolve().parents[2]
RECIPES = REPO / "recipes"

pytest.importorskip("calstation_sim")


def _run(db: Database, *, status: str = "aborted", seconds: float = 130.72,
         operator: str = "root", recipe_path: Path | None = None) -> int:
    """A run of station sim-01 as stored: its steps (the last one aborted), an initial
    calibration, a cube check with the flatness beyond the range noise."""
    t0 = dt.datetime(2026, 5, 4, 9, 0, tzinfo=dt.UTC)
    path = recipe_path or RECIPES / "sim-periodicity.yaml"
    with db.session() as s:
        from calstation.storage.db import Station

        st = s.query(Station).filter_by(name="sim-01").one_or_none() or Station(name="sim-01")
        run = Run(station=st, recipe_name="sim-periodicity", recipe_path=str(path),
                  recipe_text=path.read_text(encoding="utf-8"), recipe_sha256="ab" * 32,
                  operator=operator, unattended=False, data_dir="/nowhere/runs/x",
                  status=status, started_at=t0, finished_at=t0 + dt.timedelta(seconds=300))
        s.add(run)
        at = t0
        for name, took in (("preflight", 9.5), ("place_qa_cube", seconds)):
            s.add(Step(run=run, name=name, attempt=1, status="passed" if name == "preflight"
                       else "aborted", started_at=at,
                       finished_at=at + dt.timedelta(seconds=took), result={}))
            at += dt.timedelta(seconds=took)
        s.flush()
        s.add(Calibration(run=run, stage="initial", strategy="initial", tx=0.0147,
                          ty=1.249, tz=-0.0003, rx=0.0, ry=0.0, rz=-0.7775, sigma_tx=2.8e-5,
                          sigma_ty=2.8e-5, sigma_tz=6.4e-3, sigma_rz=3.5e-4, cost=3.93e-8,
                          iterations=1, diagnostics={}))
        s.add(CubeCheckRecord(run=run, obb_edges=[0.1, 0.1, 0.1], obb_error=0.0068,
                              face_edges=[0.1, 0.1, 0.1], edge_error=0.00002,
                              flatness_rms=0.00065, flatness_excess=0.00005,
                              perpendicularity_deg=0.05, passed=True, failures=[]))
        s.flush()
        return int(run.id)


def _recipes(folder: Path) -> Path:
    """A recipes folder like the repository's: the emulated station (slow), the simulated
    ones, the template, and a recipe that does not validate."""
    folder.mkdir(parents=True, exist_ok=True)
    for name in ("hokuyo-canopen-emulated.yaml", "sim-periodicity.yaml",
                 "sim-periodicity-both-ways.yaml", "real-station-template.yaml"):
        (folder / name).write_text((RECIPES / name).read_text(encoding="utf-8"),
                                   encoding="utf-8")
    bad = yaml.safe_load((RECIPES / "sim-periodicity.yaml").read_text())
    bad["steps"]["spin_scan"]["rpm"] = "very fast " * 300
    (folder / "broken.yaml").write_text(yaml.safe_dump(bad), encoding="utf-8")
    return folder


def test_the_start_form_offers_the_quickest_recipe_described_and_guesses_no_operator(
        tmp_path: Path, db: Database) -> None:
    recipes = _recipes(tmp_path / "recipes")
    _run(db, operator="root", recipe_path=recipes / "hokuyo-canopen-emulated.yaml")
    with db.session() as s:  # the newest run was started from another folder: not a default
        run = s.scalars(select(Run)).one()
        run.recipe_path = str(tmp_path / "elsewhere" / "hokuyo-canopen-emulated.yaml")
    client = TestClient(create_app(db, data_dir=tmp_path / "data", recipes_dir=recipes),
                        base_url="http://127.0.0.1")
    html = client.get("/").text
    menu = re.search(r"<select name=\"recipe\" id=\"recipe\" required>(.*?)</select>", html, re.S)
    assert menu is not None
    options = re.findall(r'<option value="([^"]+)"[^>]*?( selected)?>', menu.group(1))
    # the simulated station first, the quickest first; the emulated one (real time) last
    names = [name for name, _ in options]
    assert names[0] == "sim-periodicity.yaml" and names[-1] == "hokuyo-canopen-emulated.yaml"
    assert [name for name, chosen in options if chosen] == ["sim-periodicity.yaml"]
    # recipes that cannot run are not options (a reason hidden in one, a select thousands of
    # pixels wide), but a list under the form, each with its reason
    assert "broken.yaml" not in menu.group(1) and "template" not in menu.group(1)
    unrunnable = re.search(r'<details id="unrunnable">(.*?)</details>', html, re.S)
    assert unrunnable and "broken.yaml" in unrunnable.group(1)
    assert "it is a template" in unrunnable.group(1)
    # each recipe described, with its station and how long it turns
    assert "Simulated station" in html and "Station sim-01; the platter turns 6.3 s" in html
    # no operator guessed (the newest run's was a terminal's login name)
    assert re.search(r'<input name="operator" id="operator" value=""', html)


def test_the_end_screen_shows_no_limit_where_there_is_none_and_no_red_on_a_pass(
        tmp_path: Path, db: Database) -> None:
    from calstation.storage.report_html import report_data
    from calstation.web.endscreen import end_screen

    run_id = _run(db, status="passed")
    result = end_screen(report_data(db, run_id, views=False))
    html = environment().get_template("result.html").render(
        state={"result": result, "run_id": run_id})
    assert "≤ —" not in html
    row = re.search(r"<tr><td>face flatness \(RMS, range noise included\)</td>(.*?)</tr>", html)
    assert row and "no limit" in row.group(1) and "bad" not in row.group(1)


def test_the_live_header_steps_and_end_screen_agree_on_the_times(
        tmp_path: Path, db: Database) -> None:
    from calstation.storage.report_html import report_data
    from calstation.web.endscreen import end_screen
    from calstation.web.live import LiveState

    run_id = _run(db, seconds=48.0)
    live = LiveState()
    live.begin(run_id, "sim-periodicity", "ann", None, ("preflight", "place_qa_cube"))
    live.update(lambda st: st.steps["place_qa_cube"].update(
        status="running", attempt=1, started_at=time.time() - 51.0))
    live.finish("aborted", end_screen(report_data(db, run_id, views=False)), None)
    snap = live.snapshot()
    assert snap["finished_at"] - snap["started_at"] == pytest.approx(300.0)
    assert snap["result"]["elapsed_s"] == pytest.approx(300.0)
    step = next(s for s in snap["steps"] if s["name"] == "place_qa_cube")
    assert step["seconds"] == pytest.approx(48.0) and step["status"] == "aborted"


def test_the_run_page_names_steps_in_words_and_times_for_people(
        tmp_path: Path, db: Database) -> None:
    run_id = _run(db, seconds=130.72)
    client = TestClient(create_app(db, data_dir=tmp_path / "data", recipes_dir=tmp_path),
                        base_url="http://127.0.0.1")
    html = client.get(f"/runs/{run_id}").text
    steps = re.search(r'<table id="steps">(.*?)</table>', html, re.S)
    assert steps is not None
    assert "place the QA cube" in steps.group(1) and "place_qa_cube" not in steps.group(1)
    assert "2 min 11 s" in steps.group(1) and "130.72" not in steps.group(1)
    # the cost in a form no line breaks inside
    assert "3.93 × 10⁻⁸" in html and "e-08" not in html


def test_the_page_log_names_steps_in_words() -> None:
    from calstation.station.operator import StationEvent
    from calstation.web.live import LiveState, WebOperator

    live = LiveState()
    live.begin(1, "r", "ann", None, ("place_qa_cube",))
    WebOperator(live, None).event(StationEvent("step_started", {"step": "place_qa_cube",
                                                                "attempt": 1}))
    assert [line["text"] for line in live.snapshot()["log"]] == ["▶ place the QA cube"]


def test_the_history_labels_its_compare_columns(tmp_path: Path, db: Database) -> None:
    _run(db)
    client = TestClient(create_app(db, data_dir=tmp_path / "data", recipes_dir=tmp_path),
                        base_url="http://127.0.0.1")
    html = client.get("/runs").text
    head = re.search(r'<table id="history">\s*<tr>(.*?)</tr>', html, re.S)
    assert head and head.group(1).startswith(
        '<th title="compare: the run shown as A">A</th><th title="compare: the run shown as B">'
        "B</th>")


def test_an_abort_is_not_a_failure_in_the_pareto_and_its_ticks_are_round() -> None:
    from calstation.storage.dashboard_figures import ABORTED, FLAG, pareto_figure

    data = {"period": {"since": "2026-05-01", "until": "2026-05-31"}, "pareto": [
        {"reason": "cube_scan: cube edge error (face fit)", "step": "cube_scan",
         "limit": "cube edge error (face fit)", "status": "failed", "count": 3,
         "cumulative": 0.6},
        {"reason": "spin_scan: aborted", "step": "spin_scan", "limit": "aborted",
         "status": "aborted", "count": 2, "cumulative": 1.0}]}
    fig = pareto_figure(data)
    bars = fig["data"][0]
    assert bars["marker"]["color"] == [FLAG, ABORTED]
    assert bars["x"][1].endswith("aborted") and "failed" in bars["text"][0]
    assert fig["layout"]["yaxis2"]["tickvals"] == [0, 25, 50, 75, 100]


def test_the_stations_side_by_side_name_each_panel_above_it() -> None:
    from calstation.storage.dashboard_figures import comparison_figure

    rows = [{"param": p, "label": display.quantity(p).title, "short": display.quantity(p).heading,
             "stations": [{"station": s, "q1": 0.01, "median": 0.011, "q3": 0.012, "low": 0.009,
                           "high": 0.013} for s in ("line-1", "line-2")]}
            for p in ("tx", "ty", "tz", "ry", "rz")]
    fig = comparison_figure(rows)
    layout = fig["layout"]
    # no axis titles to run into the next panel: each panel's name is an annotation above it
    assert all("title" not in layout[f"yaxis{'' if i == 1 else i}"] for i in range(1, 6))
    assert [a["text"] for a in layout["annotations"]] == [r["short"] for r in rows]
    assert fig["data"][0]["median"] == [pytest.approx(11.0)] * 2  # shown in mm


def test_a_control_chart_is_scaled_to_its_points_not_to_the_drift_limit() -> None:
    from calstation.storage.dashboard import chart
    from calstation.storage.dashboard_figures import control_figure

    values = [0.01560, 0.01562, 0.01559, 0.01561, 0.01563, 0.01560, 0.01558, 0.01561, 0.01562]
    series = {"run": list(range(1, 10)), "t": [f"2026-05-0{i} 09:00" for i in range(1, 10)],
              "value": values, "limit": 0.002}
    fig = control_figure(chart(series, "sim-01", "tx"))
    lo, hi = fig["layout"]["yaxis"]["range"]
    assert hi - lo < 0.5  # mm: the points' spread, not the ±2 mm of the drift limit
    assert lo <= min(values) * 1e3 <= max(values) * 1e3 <= hi
    assert "the recipe's limit (±2.000 mm) is off the scale" in fig["layout"]["title"]["text"]


def test_a_3d_views_residuals_say_what_is_normal() -> None:
    from calstation.storage.report_html import residual_note

    note = residual_note(12000, 80000, "distance to the nearest point of the other half-turn",
                         {"median": 0.0014, "p95": 0.0035}, "half-turn")
    assert "median 1.40 mm, 95th percentile 3.50 mm" in note
    assert "is normal" in note and "predicted reconstruction error" in note


def test_the_terminal_summary_says_1_turn_and_not_estimated(db: Database) -> None:
    from rich.console import Console

    from calstation.cli._operator import render_summary
    from calstation.storage.report import get_run, run_summary

    run_id = _run(db)
    with db.session() as s:
        summary = run_summary(get_run(s, run_id))
    summary["calibrations"][0].update(accepted=True, predicted_error_m=0.000078, budget_m=0.0003,
                                      diagnostics={"predicted_error": {"turns": 1}})
    console = Console(file=io.StringIO(), width=160)
    render_summary(console, summary)
    text = console.file.getvalue()  # type: ignore[attr-defined]
    assert "after 1 turn)" in text and "1 turns" not in text
    assert "not estimated" in text and not re.search(r"│\s+0\.0000\s+│", text)
    assert math.isfinite(summary["calibrations"][0]["H"]["rz"])
