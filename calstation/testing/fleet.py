"""A fleet's database seeded from simulated recordings, for campaign tests and the fleet
benchmark (``benchmarks/fleet_reprocess.py``).

A few simulated runs give the recording files; any number of runs over several stations are
stored on them (runs share recording files, as the benchmark allows), each as the station
stores it: the run with its recipe, the scan steps, the recordings as artifacts (size, sha256),
the initial and the accepted fine calibration, and the cube check. The accepted H of each run
is what today's engine finds on its recordings plus a chosen ``change``, so a campaign's
flagged units are known in advance: exactly the runs whose change was seeded above the
tolerance.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from calstation.recipes import LoadedRecipe, load_recipe
from calstation.recordings.runfolder import file_sha256
from calstation.station.reprocess import Recomputed
from calstation.storage.db import (
    Artifact,
    Calibration,
    Database,
    Run,
    RunStatus,
    Step,
    StepStatus,
    get_or_create_station,
)

if TYPE_CHECKING:
    from calstation.engine.result import CalibrationResult

SCANS = (("static_scan", "static"), ("spin_scan", "spin"), ("cube_scan", "cube"))
"""The scan steps of a periodicity run and the kind of their recording."""


def fleet_recipe(folder: Path) -> Path:
    """``recipes/sim-periodicity.yaml`` made light for campaigns over many runs (300 returns
    per line at 400 lines a second: re-processing takes a few seconds), with ry's σ limit at
    0.2° so that today's engine accepts what it finds on these shorter scans; written to
    ``folder/fleet.yaml``."""
    import yaml

    from calstation.testing import SHIPPED_RECIPES

    data = yaml.safe_load((SHIPPED_RECIPES / "sim-periodicity.yaml").read_text())
    data["name"] = "sim-fleet"
    data["simulation"]["lidar"].update({"points_per_line": 300, "line_rate_hz": 400})
    data["calibration"]["max_sigma"] = {"ry_deg": 0.2}
    path = folder / "fleet.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def simulate_recordings(folder: Path, recipe: Path, seeds: Sequence[int]) -> list[dict[str, Path]]:
    """One simulated run of ``recipe`` per seed, in ``folder/sim-<seed>/``: its recordings
    (``static``, ``spin``, ``cube``), as the simulator (:func:`calstation.plugins.simulator`)
    writes them."""
    from calstation import plugins

    simulator = plugins.simulator()
    loaded = load_recipe(recipe)
    return [dict(simulator.simulate_run(loaded, folder / f"sim-{seed}", seed=seed,
                                        progress=False))
            for seed in seeds]


def _run_rows(loaded: LoadedRecipe, files: dict[str, Path], hashes: dict[Path, str],
              station_id: int, run_id: int | None = None) -> Run:
    """A passed periodicity run on ``files``, with its scan steps and recordings (not added)."""
    run = Run(id=run_id, station_id=station_id, recipe_name=loaded.recipe.name,
              recipe_path=str(loaded.path) if loaded.path else None, recipe_text=loaded.text,
              recipe_sha256=loaded.sha256, operator="fleet", unattended=True,
              data_dir=str(files["spin"].parent), status=RunStatus.PASSED)
    for name, kind in SCANS:
        step = Step(name=name, status=StepStatus.PASSED,
                    result={"recording": str(files[kind]), "fixture": "spin_target"})
        run.steps.append(step)
        art = Artifact(kind=kind, path=str(files[kind]), size_bytes=files[kind].stat().st_size,
                       sha256=hashes[files[kind]], status="complete")
        step.artifacts.append(art)
        run.artifacts.append(art)
    return run


def todays_result(loaded: LoadedRecipe, files: dict[str, Path]) -> Recomputed:
    """What today's engine finds on ``files`` (``calibrate --run`` of a run stored on them)."""
    from calstation.station.reprocess import compute_reprocessing, plan_reprocessing

    hashes = {files[k]: file_sha256(files[k]) for _, k in SCANS}
    run = _run_rows(loaded, files, hashes, station_id=0, run_id=0)
    return compute_reprocessing(plan_reprocessing(run))


@dataclass(frozen=True)
class FleetRecordings:
    """Simulated recordings to seed runs on: the ``recipe`` they were taken with, the
    recordings of each simulated run, and what today's engine finds on each (``today``)."""

    recipe: LoadedRecipe
    recordings: list[dict[str, Path]]
    today: list[Recomputed]


def simulate_fleet(folder: Path, seeds: Sequence[int] = (1, 3)) -> FleetRecordings:
    """:func:`fleet_recipe` simulated once per seed in ``folder``, and today's result on each
    (the seeds' true H differ: each is a unit of its own)."""
    recipe = fleet_recipe(folder)
    recordings = simulate_recordings(folder, recipe, seeds)
    loaded = load_recipe(recipe)
    return FleetRecordings(loaded, recordings, [todays_result(loaded, r) for r in recordings])


@dataclass(frozen=True)
class SeededRun:
    """A run to store: on ``station``, unit ``serial``, on the recordings number ``recordings``,
    with its accepted H = today's + ``change`` (m, rad per parameter)."""

    station: str
    serial: str
    recordings: int
    change: dict[str, float] = field(default_factory=dict)


def seed_runs(
    db: Database,
    loaded: LoadedRecipe,
    recordings: Sequence[dict[str, Path]],
    today: Sequence[Recomputed],
    runs: Sequence[SeededRun],
    *,
    start: dt.datetime | None = None,
    batch: int = 100,
) -> list[int]:
    """Store ``runs`` (see the module docstring), one minute apart from ``start``; their ids."""
    from calstation.station.persist import calibration_row, cube_row
    from calstation.station.steps.cube_scan import _cube_measurements

    t0 = start or dt.datetime(2026, 1, 5, 8, 0, tzinfo=dt.UTC)
    hashes = {f: file_sha256(f) for files in recordings for _, k in SCANS for f in [files[k]]}
    stations = {name: get_or_create_station(db, name) for name in {r.station for r in runs}}
    ids: list[int] = []
    for first in range(0, len(runs), batch):
        with db.session("seeding runs") as s:
            added = []
            for k, seeded in enumerate(runs[first:first + batch], start=first):
                done = today[seeded.recordings]
                run = _run_rows(loaded, recordings[seeded.recordings], hashes,
                                stations[seeded.station])
                run.unit_serial = seeded.serial
                run.started_at = t0 + dt.timedelta(minutes=k)
                run.finished_at = run.started_at + dt.timedelta(seconds=50)
                _add_calibrations(run, done, seeded.change, calibration_row)
                if done.cube_check is not None:
                    cube = cube_row(0, 0, None, _cube_measurements(done.cube_check))
                    cube.run_id, cube.step_id = None, None  # type: ignore[assignment]
                    run.cube_checks.append(cube)
                s.add(run)
                added.append(run)
            s.flush()
            ids += [r.id for r in added]
    return ids


def _add_calibrations(
    run: Run, done: Recomputed, change: dict[str, float],
    # Any: the rows' run_id (an int column) is cleared below, for the relationship to set
    row: Callable[[int, int | None, str, CalibrationResult], Any],
) -> None:
    """The run's initial calibration and its accepted fine one (today's H + ``change``)."""
    from dataclasses import replace

    initial = row(0, None, "initial", done.initial)
    H = done.result.H.with_(**{p: getattr(done.result.H, p) + v for p, v in change.items()})
    fine = row(0, None, "fine", replace(done.result, H=H, diagnostics={
        "gauge": done.result.diagnostics.get("gauge"),
        "covariance": done.result.diagnostics.get("covariance")}))
    fine.accepted = True
    for cal in (initial, fine):
        cal.run_id = None
        run.calibrations.append(cal)


def stored_calibrations(db: Database, run_id: int) -> list[Calibration]:
    """Every calibration of run ``run_id``, in order (for checks)."""
    from sqlalchemy import select

    with db.session("reading", read_only=True) as s:
        return list(s.scalars(select(Calibration).where(Calibration.run_id == run_id)
                              .order_by(Calibration.id)))

