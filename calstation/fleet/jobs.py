"""What a campaign's worker receives and does: one run's re-processing and its comparison,
from plain values and the recordings alone (no database), so that any Dask worker that can
reach the recordings — a path it sees, or an fsspec URL — can do it.

:func:`run_job` is exactly ``calstation calibrate --run N``'s computation
(:func:`calstation.station.reprocess.compute_reprocessing`), then the cube measured under the
new H (as the station's cube step measures it) and :func:`calstation.fleet.compare.compare`.
"""

from __future__ import annotations

import os
import socket
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

from calstation.errors import CalstationError, RecordingUnavailable
from calstation.recordings.runfolder import second_pass
from calstation.recordings.shared import StoredFile
from calstation.station.reprocess import (
    Recomputed,
    ReprocessJob,
    compute_reprocessing,
    job_recipe,
)

if TYPE_CHECKING:
    from calstation.engine.cube import CubeCheck
    from calstation.fleet.compare import CubeFigures, StoredCalibration
    from calstation.recipes import Recipe

OUTCOMES = ("reprocessed", "skipped", "failed")
"""A run's outcome in a campaign: re-processed; skipped (its recordings are missing or changed);
failed (the engine, or the run's stored data, failed)."""


@dataclass(frozen=True)
class CampaignJob:
    """One run of a campaign, as a worker receives it: the re-processing (``job``), the stored
    calibration it is compared with (:func:`calstation.fleet.compare.stored_calibration`), the
    run's stored cube figures, and its cube recordings (to measure the cube under the new H)."""

    job: ReprocessJob
    stored: StoredCalibration
    stored_cube: CubeFigures | None
    cube: StoredFile | None
    cube_pass2: StoredFile | None = None

    @property
    def run_id(self) -> int:
        """The run's id."""
        return self.job.run_id


@dataclass(frozen=True)
class JobResult:
    """What a worker sends back: the ``outcome`` (:data:`OUTCOMES`), the re-processing and its
    comparison (when re-processed), the ``error`` (when not), the seconds it took and where
    (``host:pid``)."""

    run_id: int
    outcome: str
    recomputed: Recomputed | None = None
    comparison: dict[str, object] | None = None
    error: str | None = None
    seconds: float = 0.0
    worker: str = ""


def worker_name() -> str:
    """``host:pid`` of this process."""
    return f"{socket.gethostname()}:{os.getpid()}"


def run_job(task: CampaignJob) -> JobResult:
    """Re-process ``task``'s run and compare it (see the module docstring). Never raises for the
    run's own trouble: a missing or changed recording is ``skipped``, any other failure
    ``failed``, each with its one-sentence error."""
    start = time.perf_counter()
    try:
        done = compute_reprocessing(task.job)
        comparison = _compare(task, done)
    except RecordingUnavailable as exc:
        return _ended(task, "skipped", str(exc), start)
    except CalstationError as exc:
        return _ended(task, "failed", str(exc), start)
    except Exception as exc:  # the engine's own failure, stored with the run's row
        return _ended(task, "failed", f"{type(exc).__name__}: {exc}", start)
    return JobResult(task.run_id, "reprocessed", done, comparison, None,
                     time.perf_counter() - start, worker_name())


def _ended(task: CampaignJob, outcome: str, error: str, start: float) -> JobResult:
    return JobResult(task.run_id, outcome, error=error, seconds=time.perf_counter() - start,
                     worker=worker_name())


def _compare(task: CampaignJob, done: Recomputed) -> dict[str, object]:
    """The comparison of ``done`` with the stored calibration, the cube re-measured."""
    from calstation.fleet.compare import compare, cube_figures

    loaded = job_recipe(task.job.run_id, task.job.recipe_text, task.job.recipe_path)
    new_cube = cube_figures(remeasure_cube(task, done, loaded.recipe))
    return compare(task.stored, done.result, done.refused, loaded.recipe, task.stored_cube,
                   new_cube)


def remeasure_cube(task: CampaignJob, done: Recomputed, recipe: Recipe) -> CubeCheck | None:
    """The cube check under the new H as the station's cube step does it: on both passes with
    the time offset when the cube scan had a second pass, else the check the ry combination
    measured under that H, else a check of the cube scan; None without a usable cube scan."""
    from calstation.engine.cube import check_cube, check_cube_passes
    from calstation.recordings.reader import read_recording
    from calstation.station.stored import checked_recording

    if task.cube is None:
        return None
    try:
        path = checked_recording(task.cube, task.run_id, "cube", RecordingUnavailable)
        path2 = (checked_recording(task.cube_pass2, task.run_id, second_pass("cube"),
                                   RecordingUnavailable)
                 if task.cube_pass2 is not None else None)
    except RecordingUnavailable:
        return None  # the comparison then has no new cube figures
    result = done.result
    cube, qa, radius = recipe.fixtures.qa_cube, recipe.qa, recipe.fixtures.platter.radius
    if path2 is not None:
        return check_cube_passes([read_recording(path), read_recording(path2)], result.H,
                                 cube, qa, encoder_latency_s=result.encoder_latency_s,
                                 platter_radius=radius)
    measured: CubeCheck | None = done.cube_check
    if measured is not None:
        return measured
    return check_cube(read_recording(path), result.H, cube, qa, platter_radius=radius)
