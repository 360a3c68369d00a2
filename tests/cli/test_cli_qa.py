"""QA commands: history, show, export and trend return exactly what the database holds."""

from __future__ import annotations

import csv
import datetime as dt
import io
import json
import math
import re
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from calstation.cli import _build, app
from calstation.engine.result import CalibrationResult
from calstation.storage.db import (
    Calibration,
    open_database,
)
from tests.support.qa import H1, add_run

RECIPE = Path(__file__).resolve().parents[2] / "recipes" / "sim-periodicity.yaml"


@pytest.fixture(scope="module")
def cli() -> CliRunner:
    _build_once()
    return CliRunner()


_built = False


def _build_once() -> None:
    global _built
    if not _built:
        _build()
        _built = True


@pytest.fixture
def db_url(tmp_path: Path) -> str:
    return f"sqlite:///{tmp_path / 'qa.db'}"


def test_show_json_is_what_is_stored(cli: CliRunner, db_url: str) -> None:
    db = open_database(db_url)
    t0 = dt.datetime(2026, 3, 1, 8, 30, tzinfo=dt.UTC)
    run_id = add_run(db, "st-1", "passed", H1, t0)
    res = cli.invoke(app, ["show", str(run_id), "--json", "--db", db_url])
    assert res.exit_code == 0, res.output
    shown = json.loads(res.output)
    fine = shown["calibrations"][1]
    assert fine["H"] == H1  # exact floats
    assert fine["sigma"] == {"tx": 1.234567e-5, "ty": None, "tz": 3.3e-5, "rx": None,
                             "ry": 7.1e-4, "rz": 1.9e-5}
    assert fine["accepted"] is True and fine["cost"] == 3.14159e-7 and fine["iterations"] == 9
    assert fine["diagnostics"] == {"matches": [1200, 1310], "gauge": "platter"}
    assert shown["cube_check"]["face_edges"] == [0.10004, 0.09998, 0.10003]
    assert shown["artifacts"] == [{"kind": "static", "step": "static_scan",
                                   "path": "/data/runs/x/static.mcap", "size_bytes": 123456789,
                                   "sha256": "cd" * 32, "status": "complete"}]
    assert shown["started_at"] == t0.isoformat()
    assert shown["steps"][0]["result"] == {"lines": 100}
    res = cli.invoke(app, ["show", str(run_id), "--db", db_url])
    assert res.exit_code == 0 and "PASS" in res.output
    db.dispose()


def test_show_marks_refused_reprocessing(cli: CliRunner, db_url: str) -> None:
    """A re-processing result over calibration.max_sigma is stored, never accepted, and ``show``
    says it was refused and why (table and JSON)."""
    db = open_database(db_url)
    run_id = add_run(db, "st-1", "passed", H1, dt.datetime(2026, 3, 1, tzinfo=dt.UTC))
    reason = "σ(ry) 0.31° exceeds calibration.max_sigma.ry_deg 0.2°"
    with db.session() as s:
        s.add(Calibration(run_id=run_id, stage="reprocess", strategy="shape", **H1,
                          accepted=False, diagnostics={"reprocess": {"refused": [reason]}}))
    res = cli.invoke(app, ["show", str(run_id), "--json", "--db", db_url])
    cals = json.loads(res.output)["calibrations"]
    assert [c["refused"] for c in cals] == [[], [], [reason]]
    res = cli.invoke(app, ["show", str(run_id), "--db", db_url])
    assert res.exit_code == 0, res.output
    assert "reprocess ✘ refused" in res.output
    assert "refused: " + reason in " ".join(res.output.split())
    db.dispose()


def test_history_filters_and_json(cli: CliRunner, db_url: str) -> None:
    db = open_database(db_url)
    t0 = dt.datetime(2026, 3, 1, tzinfo=dt.UTC)
    a = add_run(db, "st-1", "passed", H1, t0)
    b = add_run(db, "st-2", "failed", H1, t0 + dt.timedelta(days=2))
    c = add_run(db, "st-1", "passed", H1, t0 + dt.timedelta(days=5))

    def ids(*args: str) -> list[int]:
        res = cli.invoke(app, ["history", "--json", "--db", db_url, *args])
        assert res.exit_code == 0, res.output
        return [r["id"] for r in json.loads(res.output)]

    assert ids() == [c, b, a]
    assert ids("--station", "st-1") == [c, a]
    assert ids("--status", "failed") == [b]
    assert ids("--since", "2026-03-02") == [c, b]
    assert ids("--station", "st-1", "--since", "2026-03-04T00:00") == [c]
    res = cli.invoke(app, ["history", "--json", "--db", db_url, "--station", "st-2"])
    row = json.loads(res.output)[0]
    assert row["calibration"]["H"] == H1 and row["calibration"]["stage"] == "fine"
    assert row["status"] == "failed" and row["cube_check"]["edge_error"] == 0.0004
    res = cli.invoke(app, ["history", "--db", db_url])
    assert res.exit_code == 0 and "st-2" in res.output
    res = cli.invoke(app, ["history", "--db", db_url, "--since", "yesterday"])
    assert res.exit_code != 0
    db.dispose()


def test_export_formats_round_trip(cli: CliRunner, db_url: str, tmp_path: Path) -> None:
    db = open_database(db_url)
    run_id = add_run(db, "st-1", "passed", H1, dt.datetime(2026, 3, 1, tzinfo=dt.UTC))
    out = {}
    for fmt in ("yaml", "json", "urdf", "csv"):
        res = cli.invoke(app, ["export", str(run_id), "--format", fmt, "--db", db_url])
        assert res.exit_code == 0, res.output
        out[fmt] = res.output
    for fmt in ("yaml", "json"):
        path = tmp_path / f"c.{fmt}"
        path.write_text(out[fmt])
        loaded = CalibrationResult.load(path)
        assert loaded.H.as_dict() == H1
        assert loaded.strategy == "periodicity" and loaded.cost == 3.14159e-7
        assert loaded.sigma["tx"] == 1.234567e-5 and math.isnan(loaded.sigma["ty"])
    assert yaml.safe_load(out["yaml"])["run"]["accepted"] is True
    (row,) = list(csv.DictReader(io.StringIO(out["csv"])))
    assert {k: float(row[k]) for k in H1} == H1
    assert row["accepted"] == "true"  # as JSON, YAML and most CSV readers spell booleans
    assert row["sigma_ty"] == "" and float(row["sigma_tx"]) == 1.234567e-5
    # every σ under its own name (σ(ry) 7.1e-4 rad and σ(rz) 1.9e-5 rad were swapped once)
    assert {k: float(row[f"sigma_{k}"]) for k in ("tz", "ry", "rz")} == {
        "tz": 3.3e-5, "ry": 7.1e-4, "rz": 1.9e-5}
    assert row["strategy"] == "periodicity" and int(row["run_id"]) == run_id
    assert f'xyz="{H1["tx"]:.9g} {H1["ty"]:.9g} {H1["tz"]:.9g}"' in out["urdf"]
    res = cli.invoke(app, ["export", str(run_id), "--format", "xml", "--db", db_url])
    assert res.exit_code != 0
    db.dispose()


def test_trend_flags_drift_against_previous_accepted(
    cli: CliRunner, db_url: str, tmp_path: Path
) -> None:
    db = open_database(db_url)
    t0 = dt.datetime(2026, 3, 1, tzinfo=dt.UTC)
    # recipe limit: drift_translation 2 mm (the default); 1 mm then 3 mm steps in tx
    ids = []
    for i, tx in enumerate((0.0100, 0.0110, 0.0140)):
        ids.append(add_run(db, "st-9", "passed", {**H1, "tx": tx}, t0 + dt.timedelta(days=i)))
    add_run(db, "st-9", "failed", {**H1, "tx": 0.05}, t0 + dt.timedelta(days=9))  # not accepted
    png = tmp_path / "tx.png"
    res = cli.invoke(app, ["trend", "--station", "st-9", "--param", "tx", "--json",
                           "--png", str(png), "--db", db_url])
    assert res.exit_code == 0, res.output
    points = json.loads(res.output[: res.output.rindex("]") + 1])
    assert [p["run_id"] for p in points] == ids
    assert [p["flagged"] for p in points] == [False, False, True]
    assert points[2]["delta"] == pytest.approx(0.003)
    assert png.stat().st_size > 1000 and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    res = cli.invoke(app, ["trend", "--station", "st-9", "--param", "tx", "--png",
                           str(png), "--db", db_url])
    assert res.exit_code == 0 and "DRIFT" in res.output
    res = cli.invoke(app, ["trend", "--station", "st-9", "--param", "nope", "--db", db_url])
    assert res.exit_code != 0
    db.dispose()


def test_history_shows_serial_operator_recipe_and_reason(cli: CliRunner, db_url: str) -> None:
    db = open_database(db_url)
    t0 = dt.datetime(2026, 3, 1, tzinfo=dt.UTC)
    a = add_run(db, "st-1", "passed", H1, t0, serial="LX-1001", operator="ann")
    b = add_run(db, "st-1", "failed", H1, t0 + dt.timedelta(days=1), serial="LX-1002",
                 operator="bob", error="step spin_scan failed: the lidar went silent")
    c = add_run(db, "st-1", "failed", H1, t0 + dt.timedelta(days=2), serial="LX-1001",
                 edge_error=0.004)
    res = cli.invoke(app, ["history", "--json", "--db", db_url, "--serial", "LX-1001"])
    assert res.exit_code == 0, res.output
    rows = json.loads(res.output)
    assert [r["id"] for r in rows] == [c, a]
    assert rows[0]["unit_serial"] == "LX-1001" and rows[1]["failure_reason"] is None
    res = cli.invoke(app, ["history", "--db", db_url])
    assert res.exit_code == 0
    line_b = next(line for line in res.output.splitlines() if "LX-1002" in line)
    assert "bob" in line_b and "sim-periodicity" in line_b
    assert f"run {b} (failed): step spin_scan failed: the lidar went silent" in res.output
    assert f"run {a} " not in res.output  # a passed run has no reason line
    # a failed cube check with no run error: the reason is the cube check
    res = cli.invoke(app, ["history", "--json", "--db", db_url])
    (row_c,) = [r for r in json.loads(res.output) if r["id"] == c]
    assert row_c["failure_reason"].startswith("cube check")
    # stored names are printed as they are, not as emoji codes
    add_run(db, "st-1", "passed", H1, t0 + dt.timedelta(days=3), serial="LX-1003",
             operator=":smile:")
    res = cli.invoke(app, ["history", "--db", db_url, "--serial", "LX-1003"])
    assert ":smile:" in res.output
    db.dispose()


def test_trend_by_date_and_serial(cli: CliRunner, db_url: str, tmp_path: Path) -> None:
    from calstation.cli.history import trend_figure, trend_points

    db = open_database(db_url)
    t0 = dt.datetime(2026, 3, 1, tzinfo=dt.UTC)
    late = add_run(db, "st-5", "passed", {**H1, "tx": 0.011}, t0 + dt.timedelta(days=30),
                    serial="U-2")
    early = add_run(db, "st-5", "passed", {**H1, "tx": 0.010}, t0, serial="U-1")
    mid = add_run(db, "st-5", "passed", {**H1, "tx": 0.012}, t0 + dt.timedelta(days=3),
                   serial="U-1")
    db.dispose()
    points = trend_points("st-5", "tx", db_url)
    assert [p["run_id"] for p in points] == [early, mid, late]  # by date, not by run id
    assert [p["run_id"] for p in trend_points("st-5", "tx", db_url, serial="U-1")] == [early, mid]
    fig = trend_figure(points, "st-5", "tx")
    xs = fig.axes[0].lines[0].get_xdata()
    assert [x.date() for x in xs] == [(t0 + dt.timedelta(days=d)).date() for d in (0, 3, 30)]
    assert "run start" in fig.axes[0].get_xlabel()
    res = cli.invoke(app, ["trend", "--station", "st-5", "--param", "tx", "--serial", "U-2",
                           "--png", str(tmp_path / "t.png"), "--db", db_url])
    assert res.exit_code == 0 and "U-2" in res.output and "U-1" not in res.output


def test_show_prints_the_limits_on_pass(cli: CliRunner, db_url: str) -> None:
    db = open_database(db_url)
    run_id = add_run(db, "st-1", "passed", H1, dt.datetime(2026, 3, 1, tzinfo=dt.UTC))
    db.dispose()
    res = cli.invoke(app, ["show", str(run_id), "--db", db_url])
    text = " ".join(res.output.split())  # the console wraps long lines
    assert res.exit_code == 0 and "PASS" in text
    assert "limits: edge error ≤ 1.00 mm, OBB error ≤ 15.00 mm" in text  # the recipe's
    assert "drift ≤ 2.000 mm / 0.2000° (warns)" in text


@pytest.mark.parametrize("columns", [80, 100, 200])
def test_history_fits_the_terminal_without_splitting_a_word(
    cli: CliRunner, db_url: str, columns: int
) -> None:
    from rich.console import Console

    from calstation import display
    from calstation.cli.history import print_history

    db = open_database(db_url)
    t0 = dt.datetime(2026, 3, 1, 8, 30, tzinfo=dt.UTC)
    add_run(db, "station-with-a-long-name", "passed", H1, t0, serial="LIDAR-SERIAL-000123456",
             operator="annabelle", edge_error=0.00123)
    add_run(db, "st-2", "interrupted", {**H1, "ty": -1.25}, t0 + dt.timedelta(hours=1))
    db.dispose()
    res = cli.invoke(app, ["history", "--json", "--db", db_url])
    assert res.exit_code == 0, res.output
    # what `history` prints on a terminal `columns` wide
    console = Console(file=io.StringIO(), width=columns, emoji=False)
    print_history(json.loads(res.output), console)
    text = console.file.getvalue()  # type: ignore[attr-defined]
    lines = text.splitlines()
    assert max(len(line) for line in lines) <= columns, text
    assert "…" not in text  # nothing is cut
    words = text.split()
    # every name and every value whole, on one line: wrapped between items only
    for whole in ("station-with-a-long-name", "LIDAR-SERIAL-000123456", "annabelle",
                  "sim-periodicity", "interrupted", "2026-03-01", "08:30"):
        assert whole in words, (whole, text)
    for h in (H1, {**H1, "ty": -1.25}):
        for p in ("tx", "ty", "tz", "ry", "rz"):
            shown = display.number(p, h[p], unit=False)
            assert any(w.removesuffix("°") == shown for w in words), (p, text)
    assert "1.23" in words
    # each value is labelled: its parameter's name heads its column or stands beside it
    for p in ("tx", "ty", "tz", "ry", "rz"):
        assert re.search(rf"\b{p}\b", text), (p, text)
    if columns >= 200:  # room for everything on one line per run
        row = next(line for line in lines if "LIDAR-SERIAL-000123456" in line)
        assert "station-with-a-long-name" in row and "annabelle" in row
        assert "2026-03-01 08:30" in row
    else:  # one block per run, each value beside its name
        assert re.search(r"\bty −1250\.000 mm\b", text), text


def test_show_names_the_unit_serial_and_the_station(cli: CliRunner, db_url: str) -> None:
    db = open_database(db_url)
    t0 = dt.datetime(2026, 3, 1, 8, 30, 5, 123456, tzinfo=dt.UTC)
    known = add_run(db, "st-7", "passed", H1, t0, serial="LX-4711")
    unknown = add_run(db, "st-7", "passed", H1, t0)
    db.dispose()
    text = " ".join(cli.invoke(app, ["show", str(known), "--db", db_url]).output.split())
    assert f"run {known}: station st-7, unit serial LX-4711," in text
    assert "started 2026-03-01 08:30:05 UTC" in text and "05.123456" not in text
    text = " ".join(cli.invoke(app, ["show", str(unknown), "--db", db_url]).output.split())
    assert "unit serial — (not known)" in text
