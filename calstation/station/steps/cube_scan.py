"""The cube scan: the QA cube turning → ``cube.mcap`` (and ``cube-pass2.mcap`` with
``second_pass_rpm``), and the cube check against the recipe's ``qa`` limits under the fine
calibration. When the fine-tuning came from the spin target, the cube's side faces also measure
ry, which is combined with the spin target's (:mod:`calstation.engine.joint`) and stored as a
new fine calibration.

A failed check fails the step but keeps its recording and measurements (the outcome's
``failure``); the operator may retry it, which re-seats the cube and scans again.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable
from typing import TYPE_CHECKING

from calstation import display
from calstation.engine.result import CalibrationResult
from calstation.pipeline.judgement import budget_failure, describe, with_prediction
from calstation.pipeline.scans import Turned
from calstation.recordings.runfolder import second_pass
from calstation.station.context import RunContext
from calstation.station.operator import ProgressCallback
from calstation.station.outcome import CubeMeasurements, StepOutcome, plain
from calstation.station.recording_io import record_scan, record_second_pass, spin_acquisition
from calstation.station.steps.fine_tune import spin_as_fitted, with_stored_time_offset
from calstation.station.steps.place import place
from calstation.station.turns import more_cube_turns
from calstation.storage.db import Calibration

if TYPE_CHECKING:
    from pathlib import Path

    from calstation.engine.cube import CubeCheck
    from calstation.pipeline.stages import CubeChecked
    from calstation.recordings.recorded import Recording
    from calstation.station.prepared import PreparedScan

CUBE_SECOND_PASS = second_pass("cube")
"""File stem and artifact kind of the cube scan's second pass, measured together with the first
(the time offset's check)."""


class CubeScan:
    """Scan the QA cube and check it."""

    name = "cube_scan"

    def run(self, ctx: RunContext, step_id: int) -> StepOutcome:
        """Scan and check; the recordings, the cube check (and a combined calibration), and a
        ``failure`` when the check failed. The result holds ``after_scan_s``, how long after the
        last scan ended the result was ready (the operator's wait), and ``cube_check_s``, the
        last cube check's time."""
        d = ctx.hardware()
        cfg = ctx.recipe.steps.cube_scan
        if ctx.retrying:  # the operator's retry: re-seat the cube, rescan
            place(ctx, "qa_cube")
        path = record_scan(ctx, self.name, step_id, spin_acquisition(d, cfg),
                           more_turns=more_cube_turns(ctx))
        artifacts = [("cube", path)]
        path2 = record_second_pass(ctx, self.name, step_id, path, CUBE_SECOND_PASS)
        if path2 is not None:
            artifacts.append((CUBE_SECOND_PASS, path2))
        scan_ended = time.perf_counter()  # the run's last scan: the operator waits from here
        fine = ctx.stored_calibration("fine")
        prepared = ctx.prepared.get(path)
        made = None if prepared is None else prepared.met
        with ctx.ui.progress("cube check") as progress:
            progress("measuring the cube", 0.1)
            if made is not None and made.stage is not None and path2 is None:
                # the stage made while the scan turned, on the turns that met the budget, as
                # it is: nothing is read back (a re-processing reads the recording)
                check, joint, ry_failure = _check_cube_joint(ctx, None, fine, progress,
                                                             made.stage)
                turns = float(made.turns)
            else:
                check, joint, ry_failure, turns = _read_and_check(
                    ctx, (path, path2), fine, progress, prepared,
                    None if made is None else made.stage)
        cube = _cube_measurements(check)
        joint, budget = _budget(ctx, fine, joint, turns)
        ctx.ui.info(
            f"  cube: edge error {display.number('edge_error', check.edge_error)}, OBB error "
            f"{display.number('obb_error', check.obb_error)}, side-face twist "
            f"{display.number('twist_deg', check.twist_deg, signed=True)} "
            f"({display.sigma_text('twist_deg', check.twist_sigma_deg)}) → "
            f"{'pass' if check.passed else 'FAIL'}"
        )
        failures = list(check.failures) + [f for f in (ry_failure, budget) if f]
        if ry_failure or budget:
            cube["passed"] = False
            cube["failures"] = failures
        return StepOutcome(
            {"recording": str(path), "passed": not failures,
             "edge_error": cube["edge_error"], "obb_error": cube["obb_error"],
             "points": int(check.points),
             "after_scan_s": time.perf_counter() - scan_ended,
             "cube_check_s": float(check.timings.get("total", math.nan)),
             "joint_ry": None if joint is None else plain(joint.diagnostics["joint"]),
             "lost_lines": 0 if prepared is None else prepared.lost_lines,
             **({"turn_by_turn": plain(prepared.turns.summary)}
                if prepared is not None and prepared.turns is not None else {})},
            artifacts=artifacts,
            calibration=None if joint is None else ("fine", joint),
            cube=(None if joint is not None else fine.id, cube),
            failure=None if not failures else "cube check failed: " + "; ".join(failures),
        )


def _read_and_check(
    ctx: RunContext, paths: tuple[Path, Path | None], fine: Calibration,
    progress: ProgressCallback, prepared: PreparedScan | None, made: CubeChecked | None,
) -> tuple[CubeCheck, CalibrationResult | None, str | None, float]:
    """The cube check of the recordings at ``paths`` (the scan, its second pass or None),
    read back: cut to the turns that met the budget (the result does not depend on how many
    more the scan took while the fit was computed), with the returns as ``prepared`` while it
    turned, and the cube stage ``made`` while it turned when there is one. Returns (the check,
    the combined calibration or None, a failure or None, the whole turns used)."""
    from calstation.pipeline import turned
    from calstation.recordings.reader import read_recording

    path, path2 = paths
    cube_scan = (turned(read_recording(path)) if prepared is None else
                 turned(read_recording(path), fitted=prepared.fitted(),
                        builder=prepared.builder))
    recording = cube_scan.recording
    assert recording is not None
    check, joint, ry_failure = _check_cube_joint(ctx, cube_scan, fine, progress, made)
    if path2 is not None:
        progress("measuring the cube from both passes", 0.8)
        check = _check_cube_passes(ctx, recording, read_recording(path2), joint, fine)
    return check, joint, ry_failure, cube_scan.turns()


def _budget(
    ctx: RunContext, fine: Calibration, joint: CalibrationResult | None, turns: float
) -> tuple[CalibrationResult | None, str | None]:
    """The accuracy budget on the run's final calibration — the combination with the cube's
    faces, or the fine calibration when nothing was combined — for a spin-target strategy (a
    cube-scan strategy was judged at its fine-tuning), on the cube scan's ``turns``: (the
    combination with its predicted error recorded, or None; the refusal, with what would help,
    or None)."""
    if ctx.strategy().fixture != "spin_target":
        return joint, None
    final = joint if joint is not None else fine.result()
    final, predicted = with_prediction(final, ctx.recipe, turns=turns)
    ctx.ui.info(f"  {describe(predicted, ctx.recipe)}")
    failure = budget_failure(final, predicted, ctx.recipe, scan="cube_scan", turns=turns)
    return (final if joint is not None else None), failure


def _cube_measurements(check: CubeCheck) -> CubeMeasurements:
    """A cube check as stored (``cube_check`` row, the step's result): JSON-ready."""
    return CubeMeasurements(
        obb_edges=_numbers(check.obb_edges),
        obb_error=plain(check.obb_error),
        obb_excess=plain(check.obb_excess),
        face_edges=_numbers(check.face_edges),
        edge_error=plain(check.edge_error),
        height_judged=bool(check.height_judged),
        flatness_rms=plain(check.flatness_rms),
        flatness_excess=plain(check.flatness_excess),
        range_noise=plain(check.range_noise),
        perpendicularity_deg=plain(check.perpendicularity_deg),
        perpendicularity_sigma_deg=plain(check.perpendicularity_sigma_deg),
        twist_deg=plain(check.twist_deg),
        twist_sigma_deg=plain(check.twist_sigma_deg),
        passed=bool(check.passed),
        failures=[str(f) for f in check.failures],
    )


def _numbers(values: Iterable[float]) -> list[float | None]:
    """Numbers as JSON holds them (NaN and infinities as None)."""
    return [plain(float(v)) for v in values]


def _check_cube_passes(
    ctx: RunContext, first: Recording, second: Recording, joint: CalibrationResult | None,
    fine: Calibration,
) -> CubeCheck:
    """The cube check on both cube passes together, under the final H and the estimated
    lidar–encoder time offset (the configured latency when none was estimated)."""
    from calstation.engine.cube import check_cube_passes
    from calstation.engine.frames import Extrinsics

    H = joint.H if joint is not None else Extrinsics.from_dict(fine.params())
    latency = joint.encoder_latency_s if joint is not None else fine.encoder_latency_s
    ctx.ui.info(
        "  cube measured from both passes, "
        + ("with the configured encoder latency" if latency is None
           else f"with the estimated encoder latency {latency * 1e3:.3f} ms")
    )
    return check_cube_passes(
        [first, second], H, ctx.recipe.fixtures.qa_cube, ctx.recipe.qa,
        encoder_latency_s=latency, platter_radius=ctx.recipe.fixtures.platter.radius,
    )


def _check_cube_joint(
    ctx: RunContext, cube_scan: Turned | None, fine: Calibration, progress: ProgressCallback,
    made: CubeChecked | None = None,
) -> tuple[CubeCheck, CalibrationResult | None, str | None]:
    """The cube check, with ry combined from the spin target and the cube's side faces (the
    pipeline's cube stage, :func:`calstation.pipeline.stages.with_cube`).

    The twist of the side faces under the fine-tuned H measures ry; when the fine-tuning
    came from the spin target the two are combined (:mod:`calstation.engine.joint`) and the
    cube is measured again with the combined H. ``made``: the stage as the cube scan's fit
    within the budget made it while the scan turned, on the turns ``cube_scan`` is cut to,
    taken as it is. Returns (the check, the combined calibration or None, a failure when ry
    stays undetermined or the two disagree).
    """
    from calstation.engine.joint import joint_summary
    from calstation.pipeline import turned
    from calstation.pipeline.stages import with_cube
    from calstation.recordings.reader import read_recording

    stored = fine.result()
    spin = None
    if made is not None:  # combined by the fit within the budget (it stopped the scan)
        cubed = made
    else:
        assert cube_scan is not None, "the cube scan is read when no stage was made for it"
        if stored.range_offset is not None:  # the spin target may follow the cube's range model
            prepared = ctx.prepared.get(ctx.artifact_path("spin"))
            spin = spin_as_fitted(ctx, None if prepared is None else prepared.builder)[1]
        cubed = with_cube(ctx.recipe, ctx.strategy(), stored, cube_scan, progress, spin=spin)
        if not cubed.combined(stored):
            return cubed.check, None, cubed.ry_failure
    result = cubed.result
    result.diagnostics["from_calibration"] = fine.id
    ctx.ui.info(f"  {joint_summary(result)}")
    if result.encoder_latency_s is not None:
        # estimated again under the H whose ry the cube changed: the estimate moves a
        # little with ry (~0.08 ms per 0.1°, docs/algorithms.md); on the whole first pass,
        # which the spin scan read for the range model keeps beside its cut
        if spin is None:
            path = ctx.artifact_path("spin")
            prepared = ctx.prepared.get(path)
            spin = turned(read_recording(path),
                          builder=None if prepared is None else prepared.builder)
        result = with_stored_time_offset(ctx, result, spin, progress, " under the combined H")
    return cubed.check, result, cubed.ry_failure
