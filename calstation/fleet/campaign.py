"""A re-processing campaign: select stored runs, skip those already stored, send the rest to the
Dask cluster, store each result the moment it arrives.

:func:`run_campaign` reads top-down: find or create the campaign (:func:`open_campaign`: the
same selection and strategy continue the same campaign), select the runs, leave out those with a
row, plan the others from the database (:func:`plan_tasks`), execute them, store every result in
one transaction with its re-processing (:func:`store_result`), and mark the campaign finished
when every selected run has a row. A campaign killed at any point therefore loses at most the
runs in flight, and started again computes only the runs without a row.

Results are stored as calibrations of stage ``reprocess`` (never accepted) and a
``campaign_run`` row each (:class:`calstation.storage.db.CampaignRun`).
"""

from __future__ import annotations

import socket
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import selectinload

from calstation.errors import CalstationError, DatabaseError
from calstation.fleet.compare import cube_figures, stored_calibration
from calstation.fleet.jobs import CampaignJob, JobResult, worker_name
from calstation.fleet.selection import Selection, select_runs
from calstation.fleet.tolerance import Tolerance, flags
from calstation.recordings.runfolder import second_pass
from calstation.storage.db import (
    Calibration,
    Campaign,
    CampaignRun,
    Database,
    Run,
    utcnow,
)

if TYPE_CHECKING:
    from calstation.fleet.cluster import DaskClient
    from calstation.station.reprocess import ReprocessJob

PLAN_BATCH = 200
"""Runs read from the database at a time while planning."""

Execute = Callable[[list[CampaignJob]],
                   Iterator[tuple[CampaignJob, JobResult | None, BaseException | None]]]
"""Runs the jobs somewhere (the Dask cluster) and yields ``(job, result, error)`` as each ends."""


@dataclass
class Tally:
    """What this invocation of a campaign did so far (for the progress display)."""

    selected: int = 0
    stored_before: int = 0
    reprocessed: int = 0
    skipped: int = 0
    failed: int = 0
    flagged: int = 0
    lost: int = 0
    workers: int = 0
    started: float = field(default_factory=time.monotonic)
    ended: float | None = None
    lost_runs: list[int] = field(default_factory=list)
    before_runs: set[int] = field(default_factory=set)

    @property
    def done(self) -> int:
        """Runs given a row by this invocation."""
        return self.reprocessed + self.skipped + self.failed

    @property
    def left(self) -> int:
        """Runs still without a row."""
        return self.selected - self.stored_before - self.done

    def seconds(self) -> float:
        """How long this invocation took (so far)."""
        return (self.ended or time.monotonic()) - self.started

    def runs_per_minute(self) -> float:
        """Runs given a row per minute of this invocation."""
        elapsed = self.seconds()
        return 60.0 * self.done / elapsed if elapsed > 0 else 0.0


def open_campaign(
    db: Database, selection: Selection, tolerance: Tolerance | None, *, new: bool = False
) -> tuple[int, Tolerance]:
    """The id of the newest campaign of ``selection``'s key (a new one with ``new`` or when
    there is none) and its tolerance. A ``tolerance`` given for an existing campaign replaces
    its own, and its rows' flags are recomputed from their stored comparisons."""
    from calstation import __version__

    key = selection.key()
    with db.session("opening the campaign") as s:
        found = None if new else s.scalars(
            select(Campaign).where(Campaign.key == key).order_by(Campaign.id.desc())
        ).first()
        if found is None:
            row = Campaign(key=key, selection=selection.as_dict(), strategy=selection.strategy,
                           tolerance=(tolerance or Tolerance()).as_dict(),
                           engine=f"calstation {__version__}", host=socket.gethostname())
            s.add(row)
            s.flush()
            return row.id, tolerance or Tolerance()
        if tolerance is not None and tolerance.as_dict() != found.tolerance:
            found.tolerance = tolerance.as_dict()
            for r in found.runs:
                if r.comparison is not None:
                    r.comparison = {**r.comparison, "flags": flags(r.comparison, tolerance)}
                    r.flagged = bool(r.comparison["flags"])
        return found.id, Tolerance.from_dict(found.tolerance)


def stored_runs(db: Database, campaign_id: int) -> set[int]:
    """The runs that already have a row in the campaign."""
    with db.session("reading the campaign", read_only=True) as s:
        return set(s.scalars(select(CampaignRun.run_id)
                             .where(CampaignRun.campaign_id == campaign_id)))


def plan_tasks(
    db: Database, run_ids: list[int], strategy: str | None
) -> Iterator[CampaignJob | JobResult]:
    """For each run: its :class:`CampaignJob`, or a ``failed`` :class:`JobResult` when the
    database alone shows it cannot be re-processed (its recipe no longer loads, the strategy
    needs a scan the run does not have)."""
    from calstation.station.reprocess import plan_reprocessing

    for start in range(0, len(run_ids), PLAN_BATCH):
        batch = run_ids[start:start + PLAN_BATCH]
        with db.session("planning the campaign", read_only=True) as s:
            runs = s.scalars(select(Run).where(Run.id.in_(batch)).order_by(Run.id).options(
                selectinload(Run.steps), selectinload(Run.artifacts),
                selectinload(Run.calibrations), selectinload(Run.cube_checks)))
            for run in runs:
                try:
                    job = plan_reprocessing(run, strategy)
                except CalstationError as exc:
                    yield JobResult(run.id, "failed", error=str(exc), worker=worker_name())
                    continue
                yield _campaign_job(run, job)


def _campaign_job(run: Run, job: ReprocessJob) -> CampaignJob:
    """``job`` with what the comparison needs: the stored calibration (accepted, else the
    newest fine-tuned, else the initial), the stored cube figures, the cube recordings."""
    from calstation.station.reprocess import newest_recording

    cals = run.calibrations
    stored = ([c for c in cals if c.accepted] or [c for c in cals if c.stage == "fine"]
              or [c for c in cals if c.stage == "initial"])
    return CampaignJob(
        job=job,
        stored=stored_calibration(stored[-1]) if stored else {},
        stored_cube=cube_figures(run.cube_checks[-1]) if run.cube_checks else None,
        cube=newest_recording(run, "cube"),
        cube_pass2=newest_recording(run, second_pass("cube")),
    )


def store_result(
    db: Database, campaign_id: int, tolerance: Tolerance, result: JobResult
) -> bool:
    """Store ``result`` as the run's row of the campaign, with its re-processing (a calibration
    of stage ``reprocess``, not accepted), in one transaction. False when the run had a row
    already (another process of the same campaign stored it first)."""
    from calstation.station.reprocess import add_reprocessing

    comparison = None
    if result.comparison is not None:
        comparison = {**result.comparison, "flags": flags(result.comparison, tolerance)}
        if result.recomputed is not None:
            comparison["warnings"] = list(result.recomputed.warnings)
    try:
        with db.session("storing a campaign's result") as s:
            calibration_id = None
            if result.recomputed is not None:
                done = add_reprocessing(s, result.recomputed, accept=False)
                calibration_id = done.calibration_id
                row = s.get(Calibration, calibration_id)
                assert row is not None
                row.diagnostics = {**(row.diagnostics or {}), "campaign": campaign_id}
            s.add(CampaignRun(
                campaign_id=campaign_id, run_id=result.run_id, calibration_id=calibration_id,
                outcome=result.outcome, flagged=bool(comparison and comparison["flags"]),
                refused=bool(comparison and comparison.get("refused")), comparison=comparison,
                error=result.error, seconds=result.seconds, worker=result.worker))
    except DatabaseError as exc:
        if isinstance(exc.__cause__, IntegrityError):
            return False
        raise
    return True


def finish_campaign(db: Database, campaign_id: int, selected: int) -> bool:
    """Record how many runs were selected, and the end when every one has a row; whether it
    is finished."""
    with db.session("ending the campaign") as s:
        campaign = s.get(Campaign, campaign_id)
        assert campaign is not None
        campaign.selected = selected
        rows = len(campaign.runs)
        campaign.finished_at = utcnow() if rows >= selected else None
        return campaign.finished_at is not None


def _count(tally: Tally, result: JobResult, comparison_flagged: bool) -> None:
    setattr(tally, result.outcome, getattr(tally, result.outcome) + 1)
    tally.flagged += int(comparison_flagged)


def run_campaign(
    db: Database,
    selection: Selection,
    tolerance: Tolerance | None,
    execute: Execute,
    *,
    new: bool = False,
    progress: Callable[[Tally], None] | None = None,
) -> tuple[int, Tally]:
    """Re-process the runs of ``selection`` that have no row yet in their campaign, with
    ``execute`` (the Dask cluster); returns (the campaign's id, what this invocation did).
    ``tolerance`` None keeps the campaign's own (each recipe's drift limits for a new one)."""
    tell = progress or (lambda tally: None)
    campaign_id, tol = open_campaign(db, selection, tolerance, new=new)
    with db.session("selecting the runs", read_only=True) as s:
        run_ids = select_runs(s, selection)
    before = stored_runs(db, campaign_id)
    todo = [r for r in run_ids if r not in before]
    tally = Tally(selected=len(run_ids), stored_before=len(run_ids) - len(todo),
                  before_runs={r for r in run_ids if r in before})
    tell(tally)
    jobs: list[CampaignJob] = []
    for planned in plan_tasks(db, todo, selection.strategy):
        if isinstance(planned, JobResult):
            _keep(db, campaign_id, tol, planned, tally)
            tell(tally)
        else:
            jobs.append(planned)
    if jobs:
        for job, result, error in execute(jobs):
            if error is not None or not isinstance(result, JobResult):
                tally.lost += 1  # the worker died or the task was cancelled: not stored
                tally.lost_runs.append(job.run_id)
            else:
                _keep(db, campaign_id, tol, result, tally)
            tell(tally)
    tally.ended = time.monotonic()
    finish_campaign(db, campaign_id, len(run_ids))
    return campaign_id, tally


def _keep(db: Database, campaign_id: int, tol: Tolerance, result: JobResult,
          tally: Tally) -> None:
    """Store ``result`` and count it (a run another process stored first is counted as
    stored before)."""
    if store_result(db, campaign_id, tol, result):
        flagged = bool(result.comparison and flags(result.comparison, tol))
        _count(tally, result, flagged)
    else:
        tally.stored_before += 1
        tally.before_runs.add(result.run_id)


def dask_execute(client: DaskClient, campaign_tag: str) -> Execute:
    """:data:`Execute` on the Dask ``client``: each job is :func:`calstation.fleet.jobs.run_job`
    under the key ``reprocess-<tag>-<run id>``."""
    from calstation.fleet.cluster import completed
    from calstation.fleet.jobs import run_job

    def execute(jobs: Iterable[CampaignJob]) -> Iterator[
            tuple[CampaignJob, JobResult | None, BaseException | None]]:
        return completed(client, run_job, jobs,
                         key=lambda job: f"reprocess-{campaign_tag}-{job.run_id}")

    return execute
