"""Re-processing: calibrate a stored run again from its own recordings and recipe.

``calstation calibrate --run N`` reads the recipe text stored with run N and the recordings stored
as its artifacts (each checked against its stored sha256), runs the initial calibration on the
static scan and a fine-tuning strategy on the right spin scan, and stores the result with the run
as a calibration of stage ``"reprocess"`` — not accepted unless asked. The difference to the run's
accepted calibration is part of the result.

It is three steps, so that a campaign (:mod:`calstation.fleet`) does exactly the same on a Dask
worker: :func:`plan_reprocessing` reads what the run needs from the database into a
:class:`ReprocessJob` of plain values, :func:`compute_reprocessing` does the work from the job
alone (no database), and :func:`add_reprocessing` stores the result.

Every disagreement between a recording's own metadata and the recipe it is calibrated with
(:func:`calstation.pipeline.recording_disagreements`) is a warning naming both values.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, TypedDict

from sqlalchemy import select
from sqlalchemy.orm import Session

from calstation.engine.frames import Extrinsics
from calstation.engine.result import CalibrationResult
from calstation.errors import DatabaseError, RecordingError, RecordingUnavailable
from calstation.recipes import LoadedRecipe, parse_recipe
from calstation.recordings.runfolder import second_pass
from calstation.recordings.shared import StoredFile
from calstation.station.turns import turns_fitted
from calstation.storage.db import PARAMS, Calibration, Database, Run, RunStatus, StepStatus

if TYPE_CHECKING:
    from calstation.engine.cube import CubeCheck
    from calstation.pipeline import Scans
    from calstation.recordings.recorded import Recording

REPROCESS_STAGE = "reprocess"
"""The ``calibration.stage`` of a re-processing."""

Progress = Callable[[str, float], None]


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
    return job_recipe(run.id, run.recipe_text, run.recipe_path)


def job_recipe(run_id: int, text: str, recipe_path: str | None) -> LoadedRecipe:
    """Run ``run_id``'s recipe from its stored ``text`` and path (for its relative files)."""
    path = Path(recipe_path) if recipe_path else None
    base_dir = path.parent if path is not None else None
    return LoadedRecipe(parse_recipe(text, f"recipe of run {run_id}", base_dir), path, text)


def newest_recording(run: Run, kind: str) -> StoredFile | None:
    """The run's newest complete ``kind`` recording as stored (a partial one, a scan cut
    short, is never re-processed); None when there is none."""
    from calstation.station.stored import stored_file

    found = [a for a in run.artifacts if a.kind == kind and a.status == "complete"]
    return stored_file(found[-1]) if found else None


def stored_recording(run: Run, kind: str) -> Path:
    """The newest ``kind`` recording of ``run`` (``static``, ``spin``, ``cube``), checked against
    its stored sha256 (its shared copy when the run folder's file is gone);
    :class:`RecordingError` when missing or changed."""
    from calstation.station.stored import checked_recording

    return checked_recording(newest_recording(run, kind), run.id, kind, RecordingError)


def _spin_fixture(run: Run, loaded: LoadedRecipe) -> str:
    """The fixture of the run's spin scan: as its step recorded it, else its strategy's."""
    from calstation import plugins

    for step in reversed(run.steps):
        if step.name == "spin_scan" and step.status == StepStatus.PASSED and step.result:
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


@dataclass(frozen=True)
class ReprocessJob:
    """A stored run's re-processing as plain values, without the database (what a campaign
    sends to a Dask worker): the recipe text, the strategy, the recording the strategy runs on
    (``kind``), and the stored recordings by kind (None: none stored), ``required`` in the order
    they are checked, then ``optional`` ones (the cube scan of a spin-target strategy, whose
    absence is a warning)."""

    run_id: int
    recipe_text: str
    recipe_path: str | None
    strategy: str
    kind: str
    recordings: dict[str, StoredFile | None]
    required: tuple[str, ...]
    optional: tuple[str, ...] = ()
    turns: dict[str, float] = field(default_factory=dict)
    """kind → the whole turns the station fitted on, for a scan that went turn by turn and
    stopped on a fit within its budget (the recording holds the turns scanned while that fit
    was computed, which the station's result did not use); absent: every whole turn"""
    lines: dict[str, int] = field(default_factory=dict)
    """kind → the recording's first lines that fit saw, when its step stored them (the cut is
    then exact; else at ``turns``)"""


def plan_reprocessing(run: Run, strategy_name: str | None = None) -> ReprocessJob:
    """What re-processing ``run`` needs (see :class:`ReprocessJob`); ``strategy_name`` defaults
    to the run's recipe's ``calibration.strategy``. :class:`RecordingError` when the run holds
    no scan of the strategy's fixture."""
    from calstation import plugins

    loaded = run_recipe(run)
    rc = loaded.recipe
    name = strategy_name or rc.calibration.strategy
    strategy = plugins.strategy(name)
    kind = spin_recording_kind(_spin_fixture(run, loaded), strategy.fixture)
    required = [kind]
    if rc.calibration.start != "platter":
        required.append("static")
    if rc.steps.spin_scan.second_pass_rpm is not None and kind == "spin":
        required.append(second_pass("spin"))
    optional = ("cube",) if strategy.fixture == "spin_target" and kind != "cube" else ()
    return ReprocessJob(
        run_id=run.id, recipe_text=run.recipe_text, recipe_path=run.recipe_path,
        strategy=name, kind=kind,
        recordings={k: newest_recording(run, k) for k in (*required, *optional)},
        required=tuple(required), optional=optional,
        **_fitted_cuts(run, name == rc.calibration.strategy),
    )


class FittedCuts(TypedDict):
    """A re-processing job's ``turns`` and ``lines`` per scan kind (see :func:`_cut`)."""

    turns: dict[str, float]
    lines: dict[str, int]


def _fitted_cuts(run: Run, own: bool) -> FittedCuts:
    """The job's ``turns`` and ``lines``: the station's own strategy re-processed sees what its
    fits made while scanning saw."""
    fitted = _turns_fitted(run) if own else {}
    return {"turns": {k: float(t) for k, (t, _) in fitted.items()},
            "lines": {k: n for k, (_, n) in fitted.items() if n is not None}}


def _turns_fitted(run: Run) -> dict[str, tuple[int, int | None]]:
    """kind → (turns, lines) of each scan that stopped on a fit within its budget
    (:func:`~calstation.station.turns.turns_fitted` of the step's ``turn_by_turn`` summary)."""
    out = {}
    for step in run.steps:
        fitted = turns_fitted((step.result or {}).get("turn_by_turn"))
        kind = {"spin_scan": "spin", "cube_scan": "cube"}.get(step.name)
        if fitted is not None and kind is not None:
            out[kind] = fitted
    return out


def _cut(job: ReprocessJob, kind: str) -> tuple[int, int | None] | None:
    """What :func:`~calstation.pipeline.as_fitted` cuts ``kind``'s recording to."""
    turns = job.turns.get(kind)
    return None if turns is None else (int(turns), job.lines.get(kind))


@dataclass(frozen=True)
class Recomputed:
    """What :func:`compute_reprocessing` found: the recomputed ``initial`` and ``result`` (its
    diagnostics name the recordings, the recipe sha256, the warnings and the refusals), the
    recordings read (kind → local path), ``warnings``, ``refused`` (the observability gate's
    reasons, empty when the result meets it) and ``cube_check``: the cube measured under
    ``result.H`` when ry was combined with the cube scan (else None)."""

    run_id: int
    initial: CalibrationResult
    result: CalibrationResult
    recordings: dict[str, str]
    warnings: list[str]
    refused: list[str]
    cube_check: CubeCheck | None = None


def compute_reprocessing(
    job: ReprocessJob,
    progress: Progress | None = None,
    status: Callable[[str], object] | None = None,
) -> Recomputed:
    """Calibrate ``job``'s run again from its recordings (each checked against its sha256
    first) with its recipe, as the station did: :func:`calstation.pipeline.calibrate` — the
    initial calibration (or the platter's chord), the strategy, ry combined with the cube scan
    for a spin-target strategy, the time offset from a second pass, judged as a run judges it.
    Touches no database. :class:`RecordingUnavailable` when a required recording is missing or
    changed."""
    from calstation import plugins
    from calstation.pipeline import calibrate
    from calstation.station.stored import checked_recording

    say = status or (lambda message: None)
    loaded = job_recipe(job.run_id, job.recipe_text, job.recipe_path)
    paths = {k: checked_recording(job.recordings.get(k), job.run_id, k, RecordingUnavailable)
             for k in job.required}
    warnings: list[str] = []
    for k in job.optional:
        try:  # the cube scan adds its side faces to ry, as at the station
            paths[k] = checked_recording(job.recordings.get(k), job.run_id, k, RecordingError)
        except RecordingError as exc:
            warnings.append(f"ry from the spin target alone: {exc}")
    scans = _read_scans(job, loaded, paths, warnings, say)
    say("calibrating")
    done = calibrate(loaded.recipe, scans, plugins.strategy(job.strategy), progress)
    warnings += done.warnings
    initial = done.start
    recordings = {k: str(v) for k, v in paths.items()}
    result = replace(done.result, diagnostics={
        **done.result.diagnostics,
        "initial": {"H": initial.H.as_dict(), "timings": dict(initial.timings)},
        "reprocess": {"recordings": recordings, "warnings": warnings,
                      "recipe_sha256": loaded.sha256, "refused": done.refused},
    })
    return Recomputed(job.run_id, initial, result, recordings, warnings, done.refused,
                      done.cube_check)


def _read_scans(
    job: ReprocessJob,
    loaded: LoadedRecipe,
    paths: dict[str, Path],
    warnings: list[str],
    say: Callable[[str], object],
) -> Scans:
    """The job's recordings read (each cut to what the station's fit saw), as the pipeline
    takes them; every disagreement with the recipe appended to ``warnings``."""
    from calstation.pipeline import Scans, recording_disagreements, turned
    from calstation.recordings.reader import read_recording

    def read(kind: str) -> Recording:
        say(f"reading {paths[kind]}")
        recording = read_recording(paths[kind])
        warnings.extend(recording_disagreements(recording, loaded))
        return recording

    spin = turned(read(job.kind), fitted=_cut(job, job.kind))
    static = read("static") if "static" in paths else None
    cube = (turned(read("cube"), fitted=_cut(job, "cube"))
            if "cube" in paths and job.kind != "cube" else None)
    pass2 = second_pass("spin")
    return Scans(spin=spin, static=static, cube=cube,
                 spin_pass2=read(pass2) if pass2 in paths else None)


def reprocess_run(
    db: Database,
    run_id: int,
    strategy_name: str | None = None,
    *,
    accept: bool = False,
    progress: Progress | None = None,
    status: Callable[[str], object] | None = None,
) -> Reprocessing:
    """Calibrate run ``run_id`` again from its recordings and stored recipe; store the result.

    ``strategy_name`` defaults to the run's recipe's ``calibration.strategy``. The new
    calibration is stored with stage ``"reprocess"``; with ``accept`` it becomes the run's
    accepted calibration (only for a passed run) and the previous one is no longer accepted. A
    spin-target strategy's ry is combined with the run's cube scan, as at the station. A result
    over the recipe's ``calibration.max_sigma`` is stored but not accepted, with the reasons in
    ``refused``. ``status(message)`` is told what is being done (reading, initial calibration).
    """
    with db.session() as s:
        run = s.get(Run, run_id)
        if run is None:
            raise DatabaseError(f"no run with id {run_id} in the database")
        if accept and run.status != RunStatus.PASSED:
            raise DatabaseError(
                f"run {run_id} has status {run.status}: only a passed run has an accepted "
                "calibration, so the re-processing cannot be accepted", option="accept"
            )
        job = plan_reprocessing(run, strategy_name)
    done = compute_reprocessing(job, progress, status)
    with db.session() as s:
        return add_reprocessing(s, done, accept and not done.refused)


def add_reprocessing(s: Session, done: Recomputed, accept: bool) -> Reprocessing:
    """Add ``done`` to the session ``s`` as a calibration of stage ``reprocess`` of its run
    (accepted with ``accept``: the run's other calibrations are then no longer accepted), and
    compare it with the run's accepted calibration."""
    from calstation.station.persist import calibration_row

    run_id, result = done.run_id, done.result
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
    difference = None
    if accepted is not None:
        new = result.H.as_dict()
        difference = {p: new[p] - accepted[p] for p in PARAMS}
    return Reprocessing(
        run_id=run_id, calibration_id=row.id, accepted_now=accept, initial=done.initial,
        result=result, recordings=done.recordings, accepted=accepted, accepted_id=accepted_id,
        accepted_gauge=None if accepted_gauge is None else str(accepted_gauge),
        difference=difference, warnings=done.warnings, refused=done.refused,
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
