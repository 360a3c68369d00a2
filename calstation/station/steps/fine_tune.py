"""The fine-tuning: the recipe's strategy on the stored spin scan, from the initial calibration
(or, with ``calibration.start: platter``, from the platter's chord in the scan); with a second
pass, the lidar–encoder time offset; then the observability gate (``calibration.max_sigma``),
whose refusal the station retries from the spin target's placement."""

from __future__ import annotations

import math
import time
from typing import Any

from calstation.engine.observability import check_sigma
from calstation.engine.result import CalibrationResult
from calstation.errors import ObservabilityError
from calstation.station.context import RunContext
from calstation.station.outcome import StepOutcome, format_h, plain
from calstation.station.steps.spin_scan import SECOND_PASS


class FineTune:
    """Fine-tune H on the stored spin scan and gate it on its σ."""

    name = "fine_tune"

    def run(self, ctx: RunContext, step_id: int) -> StepOutcome:
        """Fit, report, gate; the ``fine`` calibration (:class:`ObservabilityError`, with the
        refused estimate in its details, when σ exceeds the recipe's limits)."""
        strategy = ctx.strategy()
        result = _fit(ctx, strategy)
        ctx.ui.info(f"  {strategy.name}: {format_h(result.H.as_dict())}")
        after_scan = None
        if ctx.scans.scan_ended is not None:
            # the spin scan was taken by this process: how long the operator waited for H
            after_scan = time.monotonic() - ctx.scans.scan_ended
            ctx.ui.info(f"  result ready {after_scan:.1f} s after the scan ended")
        # a spin-target strategy's ry is gated after the cube scan has added its faces to it
        later = ("ry",) if strategy.fixture == "spin_target" else ()
        try:
            check_sigma(result, ctx.recipe.calibration.max_sigma, strategy.fixture, later)
        except ObservabilityError as exc:
            # the refused estimate is kept with the failed step: nothing computed is lost
            exc.details = {"refused": {"H": result.H.as_dict(), "sigma": result.sigma}}
            raise
        return StepOutcome(
            {"strategy": strategy.name, "H": result.H.as_dict(), "cost": plain(result.cost),
             "iterations": result.iterations, "after_scan_s": after_scan,
             "prepared_while_scanning": "scan_during_scan" in result.timings},
            calibration=("fine", result),
        )


def _fit(ctx: RunContext, strategy: Any) -> CalibrationResult:
    """The strategy's result on the stored spin scan, with the time offset when there is a
    second pass; its warnings go to the operator."""
    from calstation.engine.frames import Extrinsics
    from calstation.plugins.cost_strategies import run_strategy
    from calstation.recordings.reader import read_recording

    recording = read_recording(ctx.artifact_path("spin"))
    with ctx.ui.progress(f"fine-tuning ({strategy.name})") as progress:
        if ctx.recipe.calibration.start == "platter":
            from calstation.plugins.cost_strategies import fine_tune_targetless

            result, warnings, first = fine_tune_targetless(
                strategy, recording, ctx.recipe, progress)
            ctx.ui.info(f"  start from the platter: {format_h(first.H.as_dict())} "
                        f"(chord {first.diagnostics['chord']})")
        else:
            start = ctx.stored_calibration("initial")
            result, warnings = run_strategy(
                strategy, recording, Extrinsics.from_dict(start.params()), ctx.recipe,
                progress
            )
        if ctx.recipe.steps.spin_scan.second_pass_rpm is not None:
            result = with_stored_time_offset(ctx, result, recording, progress, "")
    for warning in warnings:
        ctx.ui.warn(warning)
    return result


def with_stored_time_offset(
    ctx: RunContext, result: CalibrationResult, first: Any, progress: Any, under: str
) -> CalibrationResult:
    """``result`` with the lidar–encoder time offset from the spin scan's ``first`` pass and
    its stored second pass; ``under`` says which H, for the operator."""
    from calstation.engine.timeoffset import with_time_offset
    from calstation.recordings.reader import read_recording

    out = with_time_offset(
        result, first, read_recording(ctx.artifact_path(SECOND_PASS)),
        ctx.recipe.fixtures.platter.radius, progress,
    )
    ctx.ui.info(
        f"  lidar–encoder time offset{under}: {(out.encoder_latency_s or 0.0) * 1e3:.3f} ± "
        f"{(out.sigma_encoder_latency_s or math.nan) * 1e3:.3f} ms"
    )
    return out
