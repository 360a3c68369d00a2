"""One vocabulary: a parameter of a run is the same value in the same unit in every JSON twin
and the command line's JSON, each of which says its unit; every page and the terminal show it
through one formatter; a parameter a run did not estimate reads "not estimated" everywhere, and
is never flagged as a change."""

from __future__ import annotations

import datetime as dt
import json
import math
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from typer.testing import CliRunner

from calstation import display
from calstation.cli import _build, app
from calstation.storage.db import Calibration, CubeCheckRecord, Database, Run, Step, open_database
from calstation.web.app import create_app

RECIPE = Path(__file__).resolve().parents[2] / "recipes" / "sim-periodicity.yaml"
T0 = dt.datetime(2026, 5, 4, 9, 0, tzinfo=dt.UTC)
H = {"tx": 0.0156049, "ty": 1.2499893, "tz": 0.0017551, "rx": 0.0, "ry": 0.0060448,
     "rz": -0.7774587}
SIGMA = {"tx": 1.9e-5, "ty": 1.8e-5, "tz": 1.5e-5, "rx": None, "ry": 4.85e-4, "rz": 4.4e-5}


def _run(db: Database, *, day: int, fine: bool, ry_sigma: float | None = 4.85e-4,
         tz: float = H["tz"], tz_sigma: float | None = 1.5e-5) -> int:
    """A run of station st-9 as the station stores it: an accepted fine calibration (with
    ``fine``), else only an initial one that did not estimate ry."""
    started = T0 + dt.timedelta(days=day)
    with db.session() as s:
        from calstation.storage.db import Station

        st = s.query(Station).filter_by(name="st-9").one_or_none() or Station(name="st-9")
        run = Run(station=st, recipe_name="sim-periodicity", recipe_path=str(RECIPE),
                  recipe_text=RECIPE.read_text(encoding="utf-8"), recipe_sha256="ab" * 32,
                  operator="qa", unattended=True, data_dir="/nowhere/runs/x",
                  status="passed" if fine else "aborted", started_at=started,
                  finished_at=started + dt.timedelta(minutes=4), unit_serial=f"LX-{day}")
        step = Step(run=run, name="static_scan", status="passed", result={})
        s.add_all([run, step])
        s.flush()
        values = {**H, "tz": tz}
        if fine:
            sig = {**SIGMA, "ry": ry_sigma, "tz": tz_sigma}
            s.add(Calibration(run=run, stage="fine", strategy="periodicity", accepted=True,
                              **values, **{f"sigma_{k}": v for k, v in sig.items()},
                              cost=3.9e-8, iterations=9, diagnostics={}))
            s.add(CubeCheckRecord(run=run, obb_edges=[0.1012, 0.1009, 0.1003],
                                  obb_error=0.0012, face_edges=[0.10004, 0.09998, 0.10003],
                                  edge_error=0.0004, flatness_rms=0.00091,
                                  perpendicularity_deg=0.05, passed=True, failures=[]))
        else:  # the L-target's initial calibration: ry held at 0, tz barely known
            s.add(Calibration(run=run, step_id=step.id, stage="initial", strategy="initial",
                              **{**values, "ry": 0.0},
                              **{f"sigma_{k}": v for k, v in {**SIGMA, "ry": None,
                                                              "tz": 6.374e-3}.items()},
                              cost=0.1, iterations=1, diagnostics={}))
        s.flush()
        return int(run.id)


@pytest.fixture(scope="module")
def station(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    tmp = tmp_path_factory.mktemp("vocabulary")
    url = f"sqlite:///{tmp / 'qa.db'}"
    db = open_database(url)
    ids = [_run(db, day=d, fine=True) for d in range(3)]
    held = _run(db, day=3, fine=False, tz=H["tz"] - 2.093e-3)
    _build()
    client = TestClient(create_app(db, data_dir=tmp, recipes_dir=tmp / "recipes"),
                        base_url="http://127.0.0.1")
    yield {"db": db, "url": url, "client": client, "ids": ids, "held": held}
    db.dispose()


def _cli(url: str, *args: str) -> Any:
    res = CliRunner().invoke(app, [*args, "--db", url])
    assert res.exit_code == 0, res.output
    return res.output


@pytest.mark.parametrize("param", ["tx", "ry"])
def test_one_parameter_of_one_run_is_one_value_in_one_unit_everywhere(
        station: dict[str, Any], param: str) -> None:
    c, url, run_id = station["client"], station["url"], station["ids"][1]
    stored, unit = H[param], display.quantity(param).stored
    found: dict[str, tuple[float, str]] = {}

    trend = c.get(f"/trends.json?station=st-9&param={param}").json()["trends"][0]
    point = next(p for p in trend["points"] if p["run_id"] == run_id)
    found["/trends.json"] = (point["value"], trend["unit"])

    dash = c.get(f"/dashboard.json?station=st-9&param={param}&until=2026-05-31&days=56").json()
    chart = dash["charts"][0]
    point = next(p for p in chart["points"] if p["run"] == run_id)
    found["/dashboard.json"] = (point["value"], chart["unit"])

    page = c.get(f"/runs/{run_id}.json").json()
    found["/runs/N.json final"] = (page["final"]["H"][param], page["final"]["units"][param])
    row = next(r for r in page["calibrations"] if r["accepted"])
    found["/runs/N.json calibrations"] = (row["values"][param], row["units"][param])

    shown = json.loads(_cli(url, "show", str(run_id), "--json"))
    cal = next(x for x in shown["calibrations"] if x["accepted"])
    found["show --json"] = (cal["H"][param], cal["units"][param])

    listed = json.loads(_cli(url, "history", "--json"))
    item = next(r for r in listed if r["id"] == run_id)
    found["history --json"] = (item["calibration"]["H"][param], item["calibration"]["units"][param])

    runs = c.get("/runs.json").json()["runs"]
    item = next(r for r in runs if r["id"] == run_id)
    found["/runs.json"] = (item["calibration"]["H"][param], item["calibration"]["units"][param])

    assert all(v == (pytest.approx(stored, abs=0, rel=1e-12), unit) for v in found.values()), \
        found

    # and every page and the terminal show it as the one formatter writes it
    text = display.number(param, stored, unit=False)
    pages = {"/runs/N": c.get(f"/runs/{run_id}").text,
             "/runs": c.get("/runs").text,
             "/trends": c.get(f"/trends?station=st-9&param={param}").text,
             "/compare": c.get(f"/compare?a={station['ids'][0]}&b={run_id}").text,
             "show": _cli(url, "show", str(run_id)),
             "history": _cli(url, "history")}
    for where, body in pages.items():
        assert text in body, (where, text)


def test_a_parameter_not_estimated_reads_so_everywhere_and_is_never_flagged(
        station: dict[str, Any]) -> None:
    c, url, held, other = station["client"], station["url"], station["held"], station["ids"][2]
    page = c.get(f"/runs/{held}.json").json()
    assert set(page["final"]["not_estimated"]) == {"rx", "ry"}
    for where, body in {"/runs/N": c.get(f"/runs/{held}").text,
                        "/runs": c.get("/runs").text,
                        "show": _cli(url, "show", str(held)),
                        "history": _cli(url, "history")}.items():
        assert display.NOT_ESTIMATED in body, where
    # the history's row of that run: no 0.0000 where ry was not estimated
    row = re.search(rf'<tr class="aborted" data-run="{held}">(.*?)</tr>',
                    c.get("/runs").text, re.S)
    assert row and f'data-param="ry">{display.NOT_ESTIMATED}' in row.group(1)

    compared = c.get(f"/compare.json?a={other}&b={held}").json()["rows"]
    rows = {r["name"]: r for r in compared}
    # ry: run B did not estimate it; no difference is computed, nothing is flagged
    assert rows["ry"]["not_estimated_b"] and rows["ry"]["diff"] is None
    assert not rows["ry"]["flagged"]
    # tz moved 2.093 mm, past the 2 mm drift limit, but B's σ_tz is 6.374 mm: not a change
    assert abs(rows["tz"]["diff"]) > 2e-3 and not rows["tz"]["flagged"]
    html = c.get(f"/compare?a={other}&b={held}").text
    ry_row = re.search(r'<tr data-row="ry">(.*?)</tr>', html, re.S)
    assert ry_row and display.NOT_ESTIMATED in ry_row.group(1)
    assert 'class="diff bad"' not in html


def test_the_formatter() -> None:
    assert display.number("tx", 0.0156049) == "15.605 mm"
    assert display.number("ry", -0.0060448) == "−0.3463°"
    assert display.number("tz", -0.0000001, signed=True) == "+0.000 mm"
    assert display.number("tx", None) == display.number("tx", math.nan) == "—"
    assert display.with_sigma("tx", 0.0156049, 1.9e-5) == "15.605 ± 0.019 mm"
    assert display.with_sigma("ry", 0.0, None) == "not estimated"
    assert display.duration(4.25) == "4.3 s" and display.duration(130.72) == "2 min 11 s"
    assert display.duration(3725) == "1 h 02 min"
    assert display.count(1, "turn") == "1 turn" and display.count(3, "turn") == "3 turns"
    assert display.scientific(3.93e-8) == "3.93 × 10⁻⁸"
    assert "-" not in display.scientific(-3.93e-8)


def test_library_errors_name_no_flag_and_the_command_line_adds_its_own(
        station: dict[str, Any], capsys: pytest.CaptureFixture[str]) -> None:
    from calstation.errors import CalstationError
    from calstation.station.reprocess import reprocess_run
    from tests.support.clirun import run_cli

    held = station["held"]  # an aborted run: it has no accepted calibration
    with pytest.raises(CalstationError) as refused:
        reprocess_run(station["db"], held, None, accept=True)
    assert "--" not in str(refused.value) and refused.value.option == "accept"
    code, _, err = run_cli(["calibrate", "--run", str(held), "--accept", "--db",
                            station["url"]], capsys)
    assert code == 2
    assert f"error: --accept: run {held} has status aborted" in " ".join(err.split())


def test_the_placement_prompts_say_what_the_recipe_and_its_drawing_say() -> None:
    from calstation.recipes import load_recipe
    from calstation.station.operator import placement_prompt

    fixtures = load_recipe(RECIPE).recipe.fixtures
    cube = placement_prompt("qa_cube", fixtures.qa_cube)
    assert "94 mm from the axis (y +80 mm, z +50 mm), turned 20°" in cube, cube
    assert "anywhere" not in cube
    spin = placement_prompt("spin_target", fixtures.spin_target)
    assert "60 mm from the axis" in spin, spin
    moved = fixtures.spin_target.model_copy(update={"offset": (0.0, 0.085)})
    spin = placement_prompt("spin_target", moved)
    assert "85 mm from the axis" in spin and "60 mm" not in spin, spin
    centred = fixtures.spin_target.model_copy(update={"offset": (0.0, 0.0)})
    assert "its centre on the axis" in placement_prompt("spin_target", centred)


def test_show_says_where_the_runs_report_is(station: dict[str, Any], tmp_path: Path) -> None:
    db, run_id = station["db"], station["ids"][0]
    folder = tmp_path / "runs" / str(run_id)
    folder.mkdir(parents=True)
    (folder / "report.html").write_text("<!doctype html>", encoding="utf-8")
    with db.session() as s:
        run = s.get(Run, run_id)
        assert run is not None
        old, run.data_dir = run.data_dir, str(folder)
    try:
        text = " ".join(_cli(station["url"], "show", str(run_id)).split())
    finally:
        with db.session() as s:
            run = s.get(Run, run_id)
            assert run is not None
            run.data_dir = old
    assert f"report: {folder / 'report.html'}" in text
