"""Re-processing: calibrate a stored run again from its own recordings and recipe.

``calstation calibrate --run N`` reads the recipe text stored with run N and the recordings stored
as its artifacts (each checked against its stored sha256), runs the initial calibration on the
static scan and a fine-tuning strategy on the right spin scan, and stores the result with the run
as a calibration of stage ``"reprocess"`` — not accepted unless asked. The difference to the run's
accepted calibration is part of the result.

:func:`recording_disagreements` compares a recording's own metadata with the recipe it is
calibrated with (also for ``calibrate RECIPE --static --spin``); the recording's values are the
ones the reconstruction uses, so each disagreement is a warning naming both values.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sqlalchemy import select

from calstation.engine.frames import Extrinsics
from calstation.engine.result import CalibrationResult
from calstation.errors import DatabaseError, RecordingError
from calstation.recipes import LoadedRecipe, parse_recipe
from calstation.recordings.runfolder import second_pass
from calstation.storage.db import PARAMS, Calibration, Database, Run

if TYPE_CHECKING:
    from calstation.recordings.recorded import Recording

REPROCESS_STAGE = "reprocess"
"""The ``calibration.stage`` of a re-processing."""

Progress = Callable[[str, float], None]


def recording_disagreements(recording: Recording, loaded: LoadedRecipe) -> list[str]:
    """Where ``recording``'s metadata and the recipe differ: encoder direction, counts per
    revolution (4·ppr) and the recipe's sha256. One message per difference, naming both values
    and which one is used (the recording's: it describes the data as it was taken)."""
    rc = loaded.recipe
    name = recording.path.name
    out: list[str] = []
    enc = rc.station.encoder
    if recording.encoder_direction != enc.direction:
        out.append(
            f"{name}: encoder direction {recording.encoder_direction:+d} in the recording, "
            f"{enc.direction:+d} in the recipe (station.encoder.direction); the recording's "
            "value is used"
        )
    if recording.counts_per_revolution != 4 * enc.ppr:
        out.append(
            f"{name}: {recording.counts_per_revolution} encoder counts per revolution in the "
            f"recording, {4 * enc.ppr} in the recipe (4 × station.encoder.ppr {enc.ppr}); the "
            "recording's value is used"
        )
    recorded = str(recording.metadata.get("calstation", {}).get("recipe_sha256") or "")
    if recorded and recorded != loaded.sha256:
        out.append(
            f"{name}: taken with recipe sha256 {recorded[:12]}…, calibrated with recipe sha256 "
            f"{loaded.sha256[:12]}… (the recipe text differs from the one of the scan)"
        )
    return out


@dataclass(frozen=True)
class Reprocessing:
    """What :func:`reprocess_run` did.

    ``initial`` and ``result`` are the recomputed initial and fine-tuned calibrations;
    ``accepted`` the run's previously accepted H (None when it had none) and ``difference``
    ``result − accepted`` per parameter (m, rad); ``warnings`` every disagreement found;
    ``refused`` the observability gate's reasons, empty when the result meets it.
    """

    run_id: int
    calibration_id: int
    accepted_now: bool
    initial: CalibrationResult
    result: CalibrationResult
    recordings: dict[str, str]
    accepted: dict[str, float] | None = None
    accepted_id: int | None = None
    accepted_gauge: str | None = None
    difference: dict[str, float] | None = None
    warnings: list[str] = field(default_factory=list)
    refused: list[str] = field(default_factory=list)
    """Why the result does not meet the recipe's ``calibration.max_sigma`` (then it is stored
    but never accepted)."""


def run_recipe(run: Run) -> LoadedRecipe:
    """The recipe stored with ``run`` (the text it ran with, not the file as it is now)."""
    path = Path(run.recipe_path) if run.recipe_path else None
    base_dir = path.parent if path is not None else None
    recipe = parse_recipe(run.recipe_text, f"recipe of run {run.id}", base_dir)
    return LoadedRecipe(recipe, path, run.recipe_text)


def stored_recording(run: Run, kind: str) -> Path:
    """The newest ``kind`` recording of ``run`` (``static``, ``spin``, ``cube``), checked against
    its stored size and sha256; :class:`RecordingError` when missing or changed."""
    from calstation.station.stored import checked_recording

    # a partial recording (a scan cut short) is never re-processed
    found = [a for a in run.artifacts if a.kind == kind and a.status == "complete"]
    return checked_recording(found[-1] if found else None, run.id, kind, RecordingError)


def _spin_fixture(run: Run, loaded: LoadedRecipe) -> str:
    """The fixture of the run's spin scan: as its step recorded it, else its strategy's."""
    from calstation import plugins

    for step in reversed(run.steps):
        if step.name == "spin_scan" and step.status == "passed" and step.result:
            fixture = step.result.get("fixture")
            if isinstance(fixture, str):
                return fixture
    own = loaded.recipe.calibration.strategy
    return str(plugins.strategy(own).fixture)


def spin_recording_kind(run_strategy_fixture: str, fixture: str) -> str:
    """Which of the run's recordings a strategy needing ``fixture`` uses.

    The run's ``spin`` scan is of the fixture its own strategy needed; the ``cube`` scan is always
    of the QA cube. :class:`RecordingError` when the run holds no scan of ``fixture``.
    """
    if fixture == run_strategy_fixture:
        return "spin"
    if fixture == "qa_cube":
        return "cube"
    raise RecordingError(
        f"the run has no scan of the {fixture}: its spin scan is of the {run_strategy_fixture}"
    )


def reprocess_run(
    db: Database,
    run_id: int,
    strategy_name: str | None = None,
    *,
    accept: bool = False,
    progress: Progress | None = None,
    status: Callable[[str], Any] | None = None,
) -> Reprocessing:
    """Calibrate run ``run_id`` again from its recordings and stored recipe; store the result.

    ``strategy_name`` defaults to the run's recipe's ``calibration.strategy``. The new
    calibration is stored with stage ``"reprocess"``; with ``accept`` it becomes the run's
    accepted calibration (only for a passed run) and the previous one is no longer accepted. A
    spin-target strategy's ry is combined with the run's cube scan, as at the station. A result
    over the recipe's ``calibration.max_sigma`` is stored but not accepted, with the reasons in
    ``refused``. ``status(message)`` is told what is being done (reading, initial calibration).
    """
    from calstation import plugins
    from calstation.engine.initial import initial_calibration
    from calstation.engine.observability import problems_with_cube
    from calstation.plugins.cost_strategies import (
        fine_tune_targetless,
        fine_tune_with_cube,
        run_strategy,
    )
    from calstation.recordings.reader import read_recording

    say = status or (lambda message: None)
    with db.session() as s:
        run = s.get(Run, run_id)
        if run is None:
            raise DatabaseError(f"no run with id {run_id} in the database")
        if accept and run.status != "passed":
            raise DatabaseError(
                f"run {run_id} has status {run.status}: only a passed run has an accepted "
                "calibration, so --accept is refused"
            )
        loaded = run_recipe(run)
        rc = loaded.recipe
        name = strategy_name or rc.calibration.strategy
        strategy = plugins.strategy(name)
        kind = spin_recording_kind(_spin_fixture(run, loaded), strategy.fixture)
        targetless = rc.calibration.start == "platter"
        paths = {kind: stored_recording(run, kind)}
        if not targetless:
            paths["static"] = stored_recording(run, "static")
        warnings: list[str] = []
        if loaded.recipe.steps.spin_scan.second_pass_rpm is not None and kind == "spin":
            paths[second_pass("spin")] = stored_recording(run, second_pass("spin"))
        if strategy.fixture == "spin_target" and kind != "cube":
            try:  # the cube scan adds its side faces to ry, as at the station
                paths["cube"] = stored_recording(run, "cube")
            except RecordingError as exc:
                warnings.append(f"ry from the spin target alone: {exc}")
    say(f"reading {paths[kind]}")
    spin = read_recording(paths[kind])
    warnings += recording_disagreements(spin, loaded)
    if targetless:
        say("start from the platter's chord, then the fine-tuning")
        result, strategy_warnings, initial = fine_tune_targetless(strategy, spin, rc, progress)
    else:
        say(f"reading {paths['static']}")
        static = read_recording(paths["static"])
        warnings += recording_disagreements(static, loaded)
        say("initial calibration")
        initial = initial_calibration(static, rc.fixtures.static_target, rc.calibration.initial)
        result, strategy_warnings = run_strategy(strategy, spin, initial.H, rc, progress)
    warnings += strategy_warnings
    joint_failure = None
    if "cube" in paths and kind != "cube":
        say(f"combining ry with the cube scan {paths['cube']}")
        cube = read_recording(paths["cube"])
        warnings += recording_disagreements(cube, loaded)
        result, _, joint_failure = fine_tune_with_cube(result, cube, rc)
    pass2 = paths.get(second_pass("spin"))
    if pass2 is not None:  # under the final H (it moves a little with ry)
        from calstation.engine.timeoffset import with_time_offset

        say(f"lidar–encoder time offset with {pass2}")
        second = read_recording(pass2)
        warnings += recording_disagreements(second, loaded)
        result = with_time_offset(result, spin, second, rc.fixtures.platter.radius)
    refused = problems_with_cube(result, rc.calibration.max_sigma, joint_failure)
    recordings = {k: str(v) for k, v in paths.items()}
    result = replace(result, diagnostics={
        **result.diagnostics,
        "initial": {"H": initial.H.as_dict(), "timings": dict(initial.timings)},
        "reprocess": {"recordings": recordings, "warnings": warnings,
                      "recipe_sha256": loaded.sha256, "refused": refused},
    })
    done = _store(db, run_id, result, initial, recordings, warnings, accept and not refused)
    return replace(done, refused=refused)


def _store(
    db: Database,
    run_id: int,
    result: CalibrationResult,
    initial: CalibrationResult,
    recordings: dict[str, str],
    warnings: list[str],
    accept: bool,
) -> Reprocessing:
    """Store the re-processing with the run (one transaction) and compare it to the accepted."""
    from calstation.station.persist import calibration_row

    with db.session() as s:
        previous = s.scalars(
            select(Calibration).where(Calibration.run_id == run_id, Calibration.accepted)
            .order_by(Calibration.id.desc())
        ).first()
        accepted = previous.params() if previous is not None else None
        accepted_id = previous.id if previous is not None else None
        accepted_gauge = (previous.diagnostics or {}).get("gauge") if previous is not None else None
        row = calibration_row(run_id, None, REPROCESS_STAGE, result)
        if accepted_id is not None:
            row.diagnostics = {**(row.diagnostics or {}), "compared_to": accepted_id}
        if accept:
            for c in s.scalars(select(Calibration).where(Calibration.run_id == run_id)):
                c.accepted = False
            row.accepted = True
        s.add(row)
        s.flush()
        new_id = row.id
    difference = None
    if accepted is not None:
        new = result.H.as_dict()
        difference = {p: new[p] - accepted[p] for p in PARAMS}
    return Reprocessing(
        run_id=run_id, calibration_id=new_id, accepted_now=accept, initial=initial,
        result=result, recordings=recordings, accepted=accepted, accepted_id=accepted_id,
        accepted_gauge=None if accepted_gauge is None else str(accepted_gauge),
        difference=difference, warnings=warnings,
    )


def difference_rows(
    accepted: dict[str, float], new: Extrinsics
) -> list[tuple[str, float, float, float]]:
    """(parameter, accepted, new, new − accepted) in display units (mm, degrees), rx left out
    (the gauge)."""
    rows = []
    for p in PARAMS:
        if p == "rx":
            continue
        scale = math.degrees if p.startswith("r") else (lambda v: v * 1e3)
        a, b = accepted[p], new.as_dict()[p]
        rows.append((p, scale(a), scale(b), scale(b - a)))
    return rows
