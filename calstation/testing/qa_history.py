"""A station history for the QA dashboard: weeks of runs on several stations, seeded straight
into a database (the dashboard's browser test and ``benchmarks/qa_dashboard.py``).

Each station is the simulator's station of ``recipes/sim-periodicity.yaml`` with its own seed:
its accepted H is the simulator's true H for that seed plus the scatter of a calibration
(σ of the periodicity cost on that recipe), its cube check the simulator's typical figures with
their scatter. Failures are those a station sees, at realistic rates: the cube check over a
limit, σ above ``calibration.max_sigma``, a lidar that does not answer in preflight, an
encoder stall in the spin scan, the operator's abort; some runs repeat a step and pass. One
station can be given a drift: from a chosen day on, one parameter moves steadily away (a
loosening mount), which the control charts must flag.
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from sqlalchemy import insert

from calstation.storage.db import (
    Calibration,
    CubeCheckRecord,
    Database,
    Run,
    RunStatus,
    Step,
    StepStatus,
    get_or_create_station,
)

if TYPE_CHECKING:
    from calstation.recipes import LoadedRecipe

SIGMA = {"tx": 0.00012, "ty": 0.00010, "tz": 0.00012, "ry": math.radians(0.01),
         "rz": math.radians(0.008)}
"""The scatter of a calibration from run to run (m, rad): the periodicity cost's σ on the
simulated station."""
CUBE = {"edge_error": (0.00035, 0.0001), "obb_error": (0.0022, 0.0005),
        "flatness_rms": (0.0006, 0.0001), "perpendicularity_deg": (0.15, 0.05),
        "twist_deg": (0.0, 0.015)}
"""The cube check's typical figure and scatter (m or degrees)."""
STEPS = ("preflight", "static_scan", "spin_scan", "fine_tune", "cube_scan", "report")
FAILURES: tuple[tuple[float, str, str], ...] = (
    (0.020, "cube_scan", "QA cube check failed: face-fit edge error 1.31 mm > 1.00 mm"),
    (0.010, "cube_scan", "QA cube check failed: face flatness 1.62 mm RMS > 1.50 mm"),
    (0.012, "fine_tune", "ry: σ 0.112° > 0.100° (calibration.max_sigma.ry_deg)"),
    (0.006, "preflight", "lidar: no answer from 192.168.0.10:10940 within 2.0 s"),
    (0.004, "spin_scan", "encoder: no sample for 0.5 s while the table turned"),
)
"""(rate, failed step, error): how a run fails, as the station words it."""
ABORT_RATE = 0.005
RETRY_RATE = 0.04
"""Share of runs that repeat a step (then pass)."""
STEP_SECONDS = {"preflight": 8, "static_scan": 20, "spin_scan": 70, "fine_tune": 45,
                "cube_scan": 75, "report": 6}


@dataclass
class Drift:
    """``param`` of ``station`` moves by ``per_day`` (m or rad a day) from ``start_day``."""

    station: str
    param: str = "tz"
    per_day: float = 0.00012
    start_day: int = 42


Row = dict[str, object]
"""One table row, by column, for a bulk insert."""


@dataclass
class _Rows:
    """One station's rows by table, the ids of its runs, and the runs that drift."""

    run: list[Row] = field(default_factory=list)
    step: list[Row] = field(default_factory=list)
    calibration: list[Row] = field(default_factory=list)
    cube: list[Row] = field(default_factory=list)
    run_ids: list[int] = field(default_factory=list)
    drifting: list[int] = field(default_factory=list)


@dataclass
class History:
    """What :func:`seed_history` stored: run ids by station, the drifting runs, the end."""

    runs: dict[str, list[int]] = field(default_factory=dict)
    drifting: list[int] = field(default_factory=list)
    end: dt.datetime | None = None


def station_truths(n: int) -> list[dict[str, float]]:
    """The simulator's true H (m, rad) of ``n`` stations of ``sim-periodicity.yaml``, with
    seeds 0…n−1."""
    from calstation import plugins
    from calstation.recipes import load_recipe
    from calstation.testing import SHIPPED_RECIPES

    simulator = plugins.simulator()
    loaded = load_recipe(SHIPPED_RECIPES / "sim-periodicity.yaml")
    out = []
    for seed in range(n):
        t = simulator.truth(loaded, seed=seed)
        out.append({p: float(getattr(t, p)) for p in ("tx", "ty", "tz", "rx", "ry", "rz")})
    return out


def seed_history(db: Database, stations: Sequence[str], days: int, runs_per_day: int,
                 *, end: dt.datetime | None = None, drift: Drift | None = None,
                 seed: int = 0) -> History:
    """Store ``days`` days (ending at ``end``, default now) of ``runs_per_day`` runs a day on
    each of ``stations``; returns what was stored."""
    from calstation.recipes import load_recipe
    from calstation.testing import SHIPPED_RECIPES

    loaded = load_recipe(SHIPPED_RECIPES / "sim-periodicity.yaml")
    end = end or dt.datetime.now(dt.UTC).replace(microsecond=0)
    start = end - dt.timedelta(days=days)
    rng = np.random.default_rng(seed)
    truths = station_truths(len(stations))
    history = History(end=end)
    ids = {name: get_or_create_station(db, name) for name in stations}
    next_id = 1 + _max_run_id(db)
    for name, truth in zip(stations, truths, strict=True):
        rows = _station_rows(name, ids[name], truth, start, days, runs_per_day, rng, drift,
                             next_id, loaded)
        next_id += len(rows.run)
        history.runs[name] = list(rows.run_ids)
        history.drifting += rows.drifting
        with db.session("seeding the QA history") as s:
            for model, batch in ((Run, rows.run), (Step, rows.step),
                                 (Calibration, rows.calibration), (CubeCheckRecord, rows.cube)):
                if batch:
                    s.execute(insert(model), batch)
    return history


def _max_run_id(db: Database) -> int:
    from sqlalchemy import func, select

    with db.session("reading the runs", read_only=True) as s:
        return int(s.scalar(select(func.max(Run.id))) or 0)


def _station_rows(name: str, station_id: int, truth: dict[str, float], start: dt.datetime,
                  days: int, per_day: int, rng: np.random.Generator, drift: Drift | None,
                  first_id: int, loaded: LoadedRecipe) -> _Rows:
    """The rows of one station's runs (run, step, calibration, cube), spread over each day's
    shifts (06:00–22:00 UTC)."""
    rows = _Rows()
    run_id = first_id
    for day in range(days):
        times = np.sort(rng.uniform(6 * 3600, 22 * 3600, per_day))
        for k, sec in enumerate(times):
            t0 = start + dt.timedelta(days=day, seconds=float(sec))
            offset = 0.0
            if drift is not None and drift.station == name and day >= drift.start_day:
                offset = drift.per_day * (day - drift.start_day + (sec / 86400.0))
                rows.drifting.append(run_id)
            _one_run(rows, run_id, station_id, t0, truth, rng, offset,
                     drift.param if drift else "tz", f"{name}-U{day:03d}{k:03d}", loaded)
            run_id += 1
    return rows


def _fate(rng: np.random.Generator) -> tuple[RunStatus, str | None, str | None]:
    """(status, failed step, error) of one run."""
    u = float(rng.uniform())
    for rate, step, error in FAILURES:
        if u < rate:
            return RunStatus.FAILED, step, error
        u -= rate
    if u < ABORT_RATE:
        return RunStatus.ABORTED, STEPS[int(rng.integers(1, 5))], "aborted by the operator"
    return RunStatus.PASSED, None, None


def _one_run(rows: _Rows, run_id: int, station_id: int, t0: dt.datetime,
             truth: dict[str, float], rng: np.random.Generator, offset: float, param: str,
             serial: str, loaded: LoadedRecipe) -> None:
    status, failed, error = _fate(rng)
    retried = status == RunStatus.PASSED and float(rng.uniform()) < RETRY_RATE
    t = t0
    for name in STEPS:
        attempts = 2 if retried and name == "spin_scan" else 1
        for attempt in range(1, attempts + 1):
            secs = STEP_SECONDS[name] * float(rng.uniform(0.85, 1.3))
            st = (StepStatus.FAILED if (name == failed and status == RunStatus.FAILED)
                  or attempt < attempts
                  else StepStatus.ABORTED if name == failed else StepStatus.PASSED)
            rows.step.append({"run_id": run_id, "name": name, "attempt": attempt,
                                 "status": st, "started_at": t,
                                 "finished_at": t + dt.timedelta(seconds=secs),
                                 "error": error if name == failed else
                                 ("encoder: no sample for 0.5 s" if st == StepStatus.FAILED
                                  else None)})
            t += dt.timedelta(seconds=secs)
        if name == failed:
            break
    rows.run_ids.append(run_id)
    rows.run.append({"id": run_id, "station_id": station_id, "recipe_name": "sim-periodicity",
                        "recipe_path": str(loaded.path), "recipe_text": loaded.text,
                        "recipe_sha256": loaded.sha256, "operator": "qa-seed",
                        "unattended": False, "data_dir": f"/nonexistent/runs/{run_id}",
                        "started_at": t0, "finished_at": t, "status": status, "error": error,
                        "unit_serial": serial})
    if status == RunStatus.ABORTED or failed in ("preflight", "static_scan", "spin_scan"):
        return
    H = {p: truth[p] + (float(rng.normal(0.0, SIGMA[p])) if p in SIGMA else 0.0)
         for p in ("tx", "ty", "tz", "rx", "ry", "rz")}
    H[param] += offset
    rows.calibration.append({
        "run_id": run_id, "stage": "fine", "strategy": "periodicity+cube",
        "accepted": status == RunStatus.PASSED, "created_at": t,
        **H, **{f"sigma_{p}": SIGMA.get(p) for p in H}})
    if failed == "fine_tune":
        return
    cube = {k: float(rng.normal(m, s)) for k, (m, s) in CUBE.items()}
    cube = {k: abs(v) if k != "twist_deg" else v for k, v in cube.items()}
    if error and "edge error" in error:
        cube["edge_error"] = 0.00131
    if error and "flatness" in error:
        cube["flatness_rms"] = 0.00162
    rows.cube.append({"run_id": run_id, "obb_edges": [0.1] * 3, "face_edges": [0.1] * 3,
                         **cube, "passed": status == RunStatus.PASSED,
                         "failures": [error] if error else [], "created_at": t})
