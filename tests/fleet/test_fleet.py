"""``calstation reprocess``: campaigns over stored runs on a real Dask ``LocalCluster``.

The runs are stored as the station stores them on the simulator's recordings (runs share
recording files); each accepted H is what today's engine finds plus a seeded change, so the
flagged units are known in advance (``calstation.testing.fleet``).
"""

from __future__ import annotations

import json
import math
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import func, select

from calstation.fleet.tolerance import Tolerance, flags, parse_tolerance
from calstation.storage.db import Artifact, Calibration, CampaignRun, Database, open_database
from calstation.testing.fleet import FleetRecordings, SeededRun, seed_runs
from tests.support.clirun import run_cli

REPO = Path(__file__).resolve().parents[2]
DEG = math.pi / 180

# Seeded changes: above a 0.5 mm tolerance in the work volume, or below it
SEEDS = [
    SeededRun("line-1", "SN-001", 0),
    SeededRun("line-1", "SN-002", 1, {"tx": 0.3e-3}),          # ~0.2 mm: within
    SeededRun("line-1", "SN-003", 0, {"tx": 1.5e-3}),          # ~1 mm: flagged
    SeededRun("line-2", "SN-004", 1, {"ry": 0.5 * DEG}),       # flagged
    SeededRun("line-2", "SN-005", 0, {"rz": -0.01 * DEG}),     # within
    SeededRun("line-2", "SN-006", 1, {"tz": 2e-3}),            # flagged
]
FLAGGED = {"SN-003", "SN-004", "SN-006"}


def _seed(
    url: str, fleet: FleetRecordings, seeds: list[SeededRun] = SEEDS
) -> tuple[Database, list[int]]:
    db = open_database(url)
    return db, seed_runs(db, fleet.recipe, fleet.recordings, fleet.today, seeds)


def _flagged_in_report(html: str) -> set[str]:
    """The serials of the report's flagged-units table."""
    table = html.split('id="campaign-flagged"', 1)[1].split("</table>", 1)[0]
    return set(re.findall(r'<tr class="flagged"[^>]*><td class="text">([^<]+)</td>', table))


@pytest.fixture(params=["sqlite", "postgresql"])
def fleet_url(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[str]:
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'fleet.db'}"
        return
    url = request.getfixturevalue("postgres_url")
    from sqlalchemy import create_engine, text

    name = f"fleet_{os.getpid()}_{int(time.time() * 1e3) % 10**8}"
    admin = create_engine(url, isolation_level="AUTOCOMMIT")
    with admin.connect() as conn:
        conn.execute(text(f"CREATE DATABASE {name}"))
    yield url.rsplit("/", 1)[0] + f"/{name}"
    with admin.connect() as conn:
        conn.execute(text(f"DROP DATABASE {name} WITH (FORCE)"))
    admin.dispose()


def test_campaign_flags_exactly_the_seeded_runs_and_matches_calibrate(
    fleet_sim: FleetRecordings, fleet_url: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    db, ids = _seed(fleet_url, fleet_sim)
    report = tmp_path / "campaign.html"
    code, out, err = run_cli(["reprocess", "--db", fleet_url, "--workers", "2", "--tolerance",
                              "0.5", "--json", "--report", str(report)], capsys)
    assert code == 0, err
    data = json.loads(out)
    assert data["totals"]["selected"] == 6 and data["totals"]["reprocessed"] == 6
    assert data["totals"]["left"] == 0 and data["throughput"]["workers"] == 2
    runs = {r["serial"]: r for r in data["runs"]}
    assert {s for s, r in runs.items() if r["flagged"]} == FLAGGED
    assert all(r["outcome"] == "reprocessed" and not r["resumed"] for r in runs.values())
    # the comparison fields, per run
    r = runs["SN-003"]
    assert r["difference"]["tx"] == pytest.approx(-1.5e-3, abs=1e-12)
    assert r["change_in_work_volume_m"] > 0.5e-3 and "work volume moves" in r["flags"][0]
    # the same covariance: the prediction moves only with the lidar's distances to the work
    # volume, which the range terms' columns depend on (1.5 mm of tx: well under a micrometre)
    assert r["predicted_error"]["change_m"] == pytest.approx(0.0, abs=2e-6)
    assert r["cube"]["change"]["edge_error"] == pytest.approx(0.0, abs=1e-12)
    assert runs["SN-002"]["change_in_work_volume_m"] < 0.5e-3
    assert "re-processed 6 runs in" in err and "on 2 Dask workers" in err and "runs/min" in err
    # the report names exactly the seeded units, each linked when --link-base is given
    assert _flagged_in_report(report.read_text()) == FLAGGED

    # the same view on the web station's QA pages, each run linked to its page
    from fastapi.testclient import TestClient

    from calstation.web.app import create_app

    web = TestClient(create_app(db, data_dir=tmp_path, recipes_dir=tmp_path),
                     base_url="http://127.0.0.1:8470")
    campaign_id = data["campaign"]["id"]
    page = web.get(f"/campaigns/{campaign_id}")
    assert page.status_code == 200 and _flagged_in_report(page.text) == FLAGGED
    assert f'<a href="/runs/{ids[2]}">{ids[2]}</a>' in page.text
    twin = web.get(f"/campaigns/{campaign_id}.json").json()
    assert {r["serial"] for r in twin["flagged"]} == FLAGGED
    listed = web.get("/campaigns.json").json()["campaigns"]
    assert [(c["id"], c["rows"], c["flagged"]) for c in listed] == [(campaign_id, 6, 3)]
    assert f'href="/campaigns/{campaign_id}"' in web.get("/campaigns").text

    # identical to calibrate --run N, stored as re-processings and never accepted
    sample = ids[3]
    code, out, err = run_cli(["calibrate", "--run", str(sample), "--db", fleet_url, "--json"],
                             capsys)
    assert code == 0, err
    single = json.loads(out)
    with db.session() as s:
        cals = s.scalars(select(Calibration).where(Calibration.run_id == sample,
                                                   Calibration.stage == "reprocess")
                         .order_by(Calibration.id)).all()
        assert len(cals) == 2 and not any(c.accepted for c in cals)
        campaign_row, cli_row = cals
        assert campaign_row.params() == cli_row.params()
        assert campaign_row.sigmas() == cli_row.sigmas()
        assert (campaign_row.cost, campaign_row.iterations) == (cli_row.cost, cli_row.iterations)
        assert campaign_row.diagnostics["campaign"] == data["campaign"]["id"]
        assert single["calibration_id"] == cli_row.id
        accepted = s.scalars(select(Calibration).where(Calibration.accepted)).all()
        assert len(accepted) == 6 and all(c.stage == "fine" for c in accepted)

    # the same command continues the campaign: nothing computed again; a new tolerance
    # re-flags the stored comparisons
    code, out, err = run_cli(["reprocess", "--db", fleet_url, "--workers", "1", "--tolerance",
                              "tx=1", "--json"], capsys)
    assert code == 0, err
    again = json.loads(out)
    assert again["campaign"]["id"] == data["campaign"]["id"]
    assert again["totals"]["done_now"] == 0 and again["totals"]["stored_before"] == 6
    assert all(r["resumed"] for r in again["runs"])
    assert {r["serial"] for r in again["runs"] if r["flagged"]} == {"SN-003"}
    with db.session() as s:
        assert s.scalar(select(func.count()).select_from(CampaignRun)) == 6
    db.dispose()


def test_missing_or_changed_recordings_are_reported_and_skipped(
    fleet_sim: FleetRecordings, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    url = f"sqlite:///{tmp_path / 'fleet.db'}"
    db, ids = _seed(url, fleet_sim, SEEDS[:3])
    with db.session() as s:
        spin = s.scalars(select(Artifact).where(Artifact.run_id == ids[1],
                                                Artifact.kind == "spin")).one()
        spin.sha256 = "0" * 64
        static = s.scalars(select(Artifact).where(Artifact.run_id == ids[2],
                                                  Artifact.kind == "static")).one()
        static.path = str(tmp_path / "gone" / "static.mcap")
    report = tmp_path / "campaign.html"
    code, out, err = run_cli(["reprocess", "--db", url, "--workers", "1", "--station", "line-1",
                              "--limit", "3", "--report", str(report)], capsys)
    assert code == 0, err
    out = " ".join(out.split())
    assert "3 runs selected; 1 re-processed, 2 skipped" in out
    assert f"run {ids[1]} skipped" in out and "changed since it was stored" in out
    assert f"run {ids[2]} skipped" in out and "static.mcap is missing" in out
    with db.session() as s:
        rows = s.scalars(select(CampaignRun).order_by(CampaignRun.run_id)).all()
        assert [r.outcome for r in rows] == ["reprocessed", "skipped", "skipped"]
        assert rows[1].calibration_id is None and "000000000000" in (rows[1].error or "")
        campaign_id = rows[0].campaign_id
    # the report and the campaign's page list the skipped runs with why (no comparison)
    from fastapi.testclient import TestClient

    from calstation.web.app import create_app

    web = TestClient(create_app(db, data_dir=tmp_path, recipes_dir=tmp_path),
                     base_url="http://127.0.0.1:8470")
    page = web.get(f"/campaigns/{campaign_id}")
    for html in (report.read_text(), page.text):
        others = html.split('id="campaign-others"')[1].split("</table>")[0]
        assert others.count("<tr data-run=") == 2 and "static.mcap is missing" in others
    assert page.status_code == 200
    db.dispose()


def test_a_campaign_killed_half_way_finishes_without_redoing_stored_rows(
    fleet_sim: FleetRecordings, tmp_path: Path
) -> None:
    url = f"sqlite:///{tmp_path / 'fleet.db'}"
    db, ids = _seed(url, fleet_sim)
    argv = [sys.executable, "-c", "from calstation.cli import main; main()", "reprocess",
            "--db", url, "--workers", "1", "--json"]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    # its own process group: the kill takes the command and its Dask worker processes
    proc = subprocess.Popen(argv, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True)
    deadline = time.monotonic() + 120
    stored = 0
    try:
        while time.monotonic() < deadline and proc.poll() is None:
            with db.session(read_only=True) as s:
                stored = s.scalar(select(func.count()).select_from(CampaignRun)) or 0
            if stored >= 2:
                break
            time.sleep(0.1)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate(timeout=30)
    assert 2 <= stored < len(ids), f"killed with {stored} rows stored"
    with db.session(read_only=True) as s:
        before = {r.run_id: r.calibration_id for r in s.scalars(select(CampaignRun))}
        # a row and its re-processing are stored together: none without the other
        assert s.scalar(select(func.count()).select_from(Calibration)
                        .where(Calibration.stage == "reprocess")) == len(before)
    done = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    data = json.loads(done.stdout)
    assert data["totals"]["stored_before"] == len(before)
    assert data["totals"]["done_now"] == len(ids) - len(before)
    assert {r["run_id"] for r in data["runs"] if r["resumed"]} == set(before)
    with db.session(read_only=True) as s:
        rows = {r.run_id: r.calibration_id for r in s.scalars(select(CampaignRun))}
        assert set(rows) == set(ids) and all(rows[k] == v for k, v in before.items())
        per_run = s.execute(select(Calibration.run_id, func.count()).where(
            Calibration.stage == "reprocess").group_by(Calibration.run_id)).all()
        assert sorted(per_run) == [(i, 1) for i in ids]
    db.dispose()


@pytest.mark.parametrize(("specs", "expected"), [
    (["0.5"], Tolerance(0.5e-3)),
    (["0.5mm", "tx=0.2"], Tolerance(0.5e-3, {"tx": 0.2e-3})),
    (["volume=1", "ry=0.01deg"], Tolerance(1e-3, {"ry": 0.01 * DEG})),
])
def test_tolerances_parse(specs: list[str], expected: Tolerance) -> None:
    got = parse_tolerance(specs)
    assert got.volume_m == pytest.approx(expected.volume_m)
    assert got.parameters == pytest.approx(expected.parameters)
    assert Tolerance.from_dict(got.as_dict()) == got


@pytest.mark.parametrize("spec", ["-1", "tx=", "ry=2mm", "tx=1deg", "rx=1", "abc", "0"])
def test_bad_tolerances_say_what_is_expected(spec: str) -> None:
    from calstation.errors import FleetError

    with pytest.raises(FleetError, match="expected mm in the work volume"):
        parse_tolerance([spec])


def test_without_tolerance_the_recipes_drift_limits_apply() -> None:
    comparison: dict[str, Any] = {
        "difference": {"tx": 2.5e-3, "ty": 5e-3, "tz": 0.0, "ry": 0.3 * DEG, "rz": 0.0},
        "gauges_differ": True, "change_in_work_volume_m": 3e-3,
        "drift_limits": {"translation_m": 2e-3, "rotation_deg": 0.2},
    }
    found = flags(comparison, Tolerance())
    assert len(found) == 2 and found[0].startswith("tx changed by +2.500 mm")
    assert "ry changed by +0.3000°" in found[1]  # ty left out: the gauges differ


def test_bad_campaign_options_are_one_sentence(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    url = f"sqlite:///{tmp_path / 'fleet.db'}"
    for argv, expected in [
        (["--workers", "2", "--scheduler", "tcp://127.0.0.1:1"], "give one"),
        (["--workers", "0"], "expected 1 or more"),
        (["--status", "done"], "--status 'done'"),
        (["--since", "yesterday"], "is not a date"),
        (["--tolerance", "tx=1deg"], "--tolerance 'tx=1deg'"),
    ]:
        code, _, err = run_cli(["reprocess", "--db", url, *argv], capsys)
        assert code == 2 and expected in err and "Traceback" not in err, (argv, err)


def test_a_campaigns_json_holds_nothing_its_workers_print(
    fleet_sim: FleetRecordings, tmp_path: Path
) -> None:
    """The engine's libraries in the Dask workers write to descriptor 1 (Open3D's C++
    warnings, on a cube whose box it finds invalid): the workers' descriptor 1 is standard
    error, so `reprocess --json` prints its JSON alone."""
    url = f"sqlite:///{tmp_path / 'fleet.db'}"
    _, ids = _seed(url, fleet_sim)
    noisy = tmp_path / "noisy_worker.py"  # run by each worker as it starts (a Dask preload)
    noisy.write_text("import os\nos.write(1, b'[a library in a worker on descriptor 1]\\n')\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path),
           "DASK_DISTRIBUTED__WORKER__PRELOAD": json.dumps([str(noisy)])}
    done = subprocess.run([sys.executable, "-c", "from calstation.cli import main; main()",
                           "reprocess", "--db", url, "--workers", "1", "--json"],
                          env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "a library in a worker" in done.stderr, done.stdout[:300]  # it did print: there
    assert json.loads(done.stdout)["totals"]["done_now"] == len(ids)
