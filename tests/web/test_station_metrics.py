"""``/metrics`` of the web station: scraped over HTTP from a real server and parsed with
prometheus_client's own parser, after a simulated run."""

from __future__ import annotations

import datetime as dt
import math
import urllib.request
from pathlib import Path
from typing import Any

import pytest
import yaml
from prometheus_client.parser import text_string_to_metric_families
from sqlalchemy import select

from calstation.engine.accuracy import predicted_error
from calstation.engine.frames import Extrinsics
from calstation.recipes import load_recipe
from calstation.station.runs import start_run
from calstation.storage.db import Calibration, Step, open_database
from calstation.web.app import create_app
from tests.support.station import ScriptedOperator, StationTestPlugin, toy_recipe
from tests.support.webstation import served


def _scrape(url: str) -> dict[str, dict[tuple[tuple[str, str], ...], float]]:
    """Samples by name, then by sorted labels."""
    with urllib.request.urlopen(f"{url}/metrics", timeout=30) as response:
        assert response.headers["Content-Type"].startswith("text/plain")
        text = response.read().decode()
    out: dict[str, dict[tuple[tuple[str, str], ...], float]] = {}
    for family in text_string_to_metric_families(text):
        for sample in family.samples:
            out.setdefault(sample.name, {})[tuple(sorted(sample.labels.items()))] = sample.value
    return out


def _get(samples: dict[str, Any], name: str, **labels: str) -> float:
    return float(samples[name][tuple(sorted(labels.items()))])


def test_metrics_are_scraped_and_parsed(
    tmp_path: Path, station_plugin: StationTestPlugin
) -> None:
    recipe = toy_recipe(tmp_path)
    recipes = tmp_path / "recipes"
    recipes.mkdir()
    (recipes / "lean.yaml").write_text(recipe.read_text())
    db = open_database(f"sqlite:///{tmp_path / 'st.db'}")
    run_id, status = start_run(load_recipe(recipe), db, ScriptedOperator(), operator="ann",
                               data_dir=tmp_path)
    assert status == "passed"
    app = create_app(db, data_dir=tmp_path, recipes_dir=recipes)
    with served(app) as url:
        m = _scrape(url)
        assert _get(m, "calstation_runs", station="sim-test", status="passed") == 1
        steps = {dict(k)["step"] for k in m["calstation_step_duration_seconds_count"]}
        assert {"preflight", "static_scan", "spin_scan", "fine_tune", "cube_scan",
                "report"} <= steps
        assert _get(m, "calstation_step_duration_seconds_count", station="sim-test",
                    step="spin_scan") == 1
        assert _get(m, "calstation_step_duration_seconds_bucket", station="sim-test",
                    step="spin_scan", le="+Inf") == 1
        assert _get(m, "calstation_step_duration_seconds_sum", station="sim-test",
                    step="spin_scan") > 0
        assert _get(m, "calstation_cycle_time_seconds_count", station="sim-test",
                    status="passed") == 1
        with db.session() as s:
            cal = s.scalars(select(Calibration).where(Calibration.accepted)).one()
            H, sigma = cal.params(), cal.sigmas()
            covariance = (cal.diagnostics or {}).get("covariance")
        for p in ("tx", "ty", "tz"):
            assert _get(m, "calstation_accepted_translation_metres", station="sim-test",
                        param=p) == H[p]
        assert _get(m, "calstation_accepted_rotation_radians", station="sim-test",
                    param="rz") == H["rz"]
        assert _get(m, "calstation_accepted_sigma_metres", station="sim-test",
                    param="tx") == sigma["tx"]
        expected = predicted_error(
            Extrinsics.from_dict(H), {p: math.nan if v is None else v for p, v in sigma.items()},
            covariance, radius=0.585 / 2, height=0.15).max_m
        assert _get(m, "calstation_predicted_error_metres", station="sim-test",
                    param="all") == pytest.approx(expected)
        assert _get(m, "calstation_predicted_error_metres", station="sim-test",
                    param="tx") > 0
        assert _get(m, "calstation_accepted_run", station="sim-test") == run_id
        assert _get(m, "calstation_drift", station="sim-test", param="tz") == 0
        assert _get(m, "calstation_busy") == 0

        # a report that flagged drift, a step still running, then its end: the histogram
        # counts each finished attempt once, and waits for the running one
        now = dt.datetime.now(dt.UTC)
        with db.session() as s:
            report = s.scalars(select(Step).where(Step.name == "report")).one()
            report.result = {**(report.result or {}),
                             "drift": {"previous_run": 0, "delta": {}, "flagged": ["tz"]}}
            s.add(Step(run_id=run_id, name="spin_scan", attempt=9, status="running",
                       started_at=now))
            s.add(Step(run_id=run_id, name="preflight", attempt=9, status="passed",
                       started_at=now, finished_at=now + dt.timedelta(seconds=3)))
        app.state.runner._lock.acquire()
        try:
            m = _scrape(url)
            assert _get(m, "calstation_busy") == 1
        finally:
            app.state.runner._lock.release()
        assert _get(m, "calstation_drift", station="sim-test", param="tz") == 1
        assert _get(m, "calstation_step_duration_seconds_count", station="sim-test",
                    step="preflight") == 1  # behind a running step: not yet
        with db.session() as s:
            running = s.scalars(select(Step).where(Step.status == "running")).one()
            running.status, running.finished_at = "failed", now + dt.timedelta(seconds=7)
        m = _scrape(url)
        assert _get(m, "calstation_step_duration_seconds_count", station="sim-test",
                    step="preflight") == 2
        assert _get(m, "calstation_step_duration_seconds_count", station="sim-test",
                    step="spin_scan") == 2
        assert _get(m, "calstation_step_duration_seconds_bucket", station="sim-test",
                    step="spin_scan", le="10") >= 1
    db.dispose()


def test_metrics_cover_only_the_stations_of_the_servers_recipes(tmp_path: Path) -> None:
    from calstation.web.app import recipe_stations

    recipes = tmp_path / "recipes"
    recipes.mkdir()
    for name, station in (("a.yaml", "line-1"), ("b.yaml", "line-2"), ("c.yaml", "line-1")):
        (recipes / name).write_text(yaml.safe_dump({"station": {"id": station}}))
    (recipes / "broken.yaml").write_text("station: [")
    assert recipe_stations(recipes) == ["line-1", "line-2"]
    assert recipe_stations(tmp_path / "none") == []
