"""The report step: the run's verdict (the cube check, and the drift since the station's previous
accepted calibration when ``qa.drift_fails``), ``report.json`` and ``calibration.yaml``.

The verdict, the accepted calibration and both files are stored in the step's one transaction;
the files are written under temporary names and moved into place only once that transaction is
committed, so report.json never claims a verdict the database does not hold.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import TypedDict

from calstation.atomic import stage
from calstation.jsonvalue import JSONObject
from calstation.recipes import QALimits
from calstation.station import stored
from calstation.station.context import RunContext
from calstation.station.outcome import StepOutcome, plain
from calstation.storage.db import Calibration, Run, RunStatus
from calstation.storage.report import previous_accepted, run_summary


class Report:
    """Judge the run and write its report files."""

    name = "report"

    def run(self, ctx: RunContext, step_id: int) -> StepOutcome:
        """report.json and calibration.yaml, carrying the verdict the database will hold."""
        from calstation.storage.report import export_calibration

        verdict = stored.cube_verdict(ctx.db, ctx.run_id)
        drift_failure: str | None = None
        with ctx.db.session("preparing the report") as s:
            run = s.get(Run, ctx.run_id)
            assert run is not None
            fine = [c for c in run.calibrations if c.stage == "fine"]
            prev = previous_accepted(s, run) if fine else None
            drift = _drift(fine[-1], prev, ctx.recipe.qa) if prev is not None else None
            if drift is not None and drift["flagged"] and ctx.recipe.qa.drift_fails \
                    and verdict == RunStatus.PASSED:
                verdict = RunStatus.FAILED
                drift_failure = (
                    f"calibration drifted beyond the recipe's limits since run "
                    f"{drift['previous_run']}: {', '.join(drift['flagged'])} "
                    "(qa.drift_fails is set)"
                )
            accept = fine[-1].id if fine and verdict == RunStatus.PASSED else None
            run.status = verdict  # as the step's transaction will store it; not committed here
            for c in run.calibrations:
                c.accepted = c.id == accept
            summary = run_summary(run)
            text = export_calibration(run, "yaml") if fine else None
            s.rollback()
        staged = _stage_files(ctx.run_dir, summary, text)
        result: JSONObject = {"verdict": verdict, "report": str(staged[0][2])}
        if drift is not None:
            result["drift"] = plain(drift)
            if drift["flagged"]:
                ctx.ui.warn(
                    "calibration drifted beyond the recipe's limits since run "
                    f"{drift['previous_run']}: {', '.join(drift['flagged'])}"
                )
        return StepOutcome(result, staged=staged, run_status=verdict, accept_calibration=accept,
                           drift_failure=drift_failure)


def _stage_files(
    run_dir: Path, summary: Mapping[str, object], calibration_yaml: str | None
) -> list[tuple[str, Path, Path]]:
    """report.json (first) and calibration.yaml (when there is a fine calibration), written
    under temporary names: (kind, temporary file, final path)."""
    staged: list[tuple[str, Path, Path]] = []
    report = run_dir / "report.json"
    staged.append(("report", _write_staged(report, json.dumps(summary, indent=2) + "\n"),
                   report))
    if calibration_yaml is not None:
        calib = run_dir / "calibration.yaml"
        staged.append(("calibration", _write_staged(calib, calibration_yaml), calib))
    return staged


def _write_staged(final: Path, text: str) -> Path:
    """Write ``text`` beside ``final`` under a temporary name (flushed to disk); its path
    (:func:`calstation.atomic.stage`; the journal puts it in place once the step is stored)."""
    return stage(final, text, final.name)


class Drift(TypedDict):
    """How the calibration moved since the previous accepted one (m, rad) and which parameters
    moved beyond the recipe's limits."""

    previous_run: int
    delta: dict[str, float]
    flagged: list[str]


def _drift(current: Calibration, previous: Calibration, qa: QALimits) -> Drift:
    """Differences to the previous accepted calibration and which exceed the recipe's limits."""
    deltas = {p: current.params()[p] - previous.params()[p] for p in current.params()}
    flagged = [
        p for p, d in deltas.items()
        if (p.startswith("t") and abs(d) > qa.drift_translation)
        or (p.startswith("r") and abs(math.degrees(d)) > qa.drift_rotation_deg)
    ]
    return Drift(previous_run=previous.run_id, delta=deltas, flagged=flagged)
