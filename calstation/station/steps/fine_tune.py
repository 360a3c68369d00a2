"""The fine-tuning: the recipe's strategy on the stored spin scan, from the initial calibration
(or, with ``calibration.start: platter``, from the platter's chord in the scan: the start and
strategy stages of :mod:`calstation.pipeline`) — or the fit made while the scan was taken, when
it covers the whole scan; with a second pass, the lidar–encoder time offset; then the gate: the
predicted reconstruction error against the accuracy budget (``calibration.accuracy``), and any
``calibration.max_sigma`` limit. A refusal says what would help, and the station retries from
the spin target's placement."""

from __future__ import annotations

import time

from calstation import display
from calstation.engine.accuracy import PredictedError
from calstation.engine.observability import check_sigma
from calstation.engine.result import CalibrationResult
from calstation.engine.spinscan import SpinScanBuilder
from calstation.errors import ObservabilityError
from calstation.pipeline.judgement import budget_failure, describe, with_prediction
from calstation.pipeline.scans import Turned
from calstation.plugins.cost_strategies import Strategy
from calstation.station.context import RunContext
from calstation.station.operator import ProgressCallback
from calstation.station.outcome import StepOutcome, format_h, plain
from calstation.station.steps.spin_scan import SECOND_PASS
from calstation.station.turns import spin_fitted_later


class FineTune:
    """Fine-tune H on the stored spin scan and gate it on the accuracy budget (and on any
    ``calibration.max_sigma`` limit)."""

    name = "fine_tune"

    def run(self, ctx: RunContext, step_id: int) -> StepOutcome:
        """Fit, report, gate; the ``fine`` calibration (:class:`ObservabilityError`, with the
        refused estimate in its details, when it is refused)."""
        strategy = ctx.strategy()
        result, turns = _fitted(ctx, strategy)
        result, predicted = with_prediction(result, ctx.recipe, turns=turns)
        ctx.ui.info(f"  {strategy.name}: {format_h(result.H.as_dict(), result.sigma)}")
        ctx.ui.info(f"  {describe(predicted, ctx.recipe)}")
        after_scan = None
        if ctx.scans.scan_ended is not None:
            # the spin scan was taken by this process: how long the operator waited for H
            after_scan = time.monotonic() - ctx.scans.scan_ended
            ctx.ui.info(f"  result ready {after_scan:.1f} s after the scan ended")
        try:
            _gate(ctx, strategy, result, predicted, turns)
        except ObservabilityError as exc:
            # the refused estimate is kept with the failed step: nothing computed is lost
            exc.details = {"refused": {"H": result.H.as_dict(), "sigma": result.sigma,
                                       "predicted_error_m": predicted.max_m}}
            raise
        return StepOutcome(
            {"strategy": strategy.name, "H": plain(result.H.as_dict()), "cost": plain(result.cost),
             "iterations": result.iterations, "after_scan_s": after_scan,
             "prepared_while_scanning": "scan_during_scan" in result.timings,
             "turns": turns, "predicted_error_m": plain(predicted.max_m),
             "budget_m": ctx.recipe.calibration.accuracy.max_error},
            calibration=("fine", result),
        )


def _gate(
    ctx: RunContext, strategy: Strategy, result: CalibrationResult, predicted: PredictedError,
    turns: float,
) -> None:
    """Refuse ``result`` when a ``calibration.max_sigma`` limit or the accuracy budget does not
    hold. A spin-target strategy's ry is combined with the cube's faces at the cube step, which
    gates the result again: here only what the cube cannot help with must hold."""
    spin_target = strategy.fixture == "spin_target"
    later = ("ry",) if spin_target else ()
    check_sigma(result, ctx.recipe.calibration.max_sigma, strategy.fixture, later)
    if predicted.max_m <= ctx.recipe.calibration.accuracy.max_error:
        return
    judged, judged_on = result, predicted
    if spin_target:
        _, judged_on = with_prediction(result, ctx.recipe, known=("ry",))
        if judged_on.max_m <= ctx.recipe.calibration.accuracy.max_error:
            ctx.ui.info("  above the budget with the spin target's ry alone: the cube step "
                        "adds the cube's side faces to ry and decides")
            return
    failure = budget_failure(judged, judged_on, ctx.recipe, scan="spin_scan", turns=turns)
    if failure is not None:
        raise ObservabilityError(f"the {strategy.name} fine-tuning does not reach the accuracy "
                                 f"budget: {failure}")


def _fitted(ctx: RunContext, strategy: Strategy) -> tuple[CalibrationResult, float]:
    """The fine-tuning and the whole turns it used: the fit made while the spin scan was taken
    when it met the budget (with the time offset added when there is a second pass), else the
    pipeline's start and strategy stages on the stored recording."""
    from calstation.pipeline import turned
    from calstation.recordings.reader import read_recording

    path = ctx.artifact_path("spin")
    prepared = ctx.prepared.get(path)
    builder = None if prepared is None else prepared.builder
    met = None if prepared is None else prepared.met
    if met is not None:
        ctx.ui.info(f"  the fit made while scanning, on the first {met.turns} "
                    f"turn{'s' if met.turns > 1 else ''}, met the budget")
        result = met.result
        if ctx.recipe.steps.spin_scan.second_pass_rpm is not None:
            with ctx.ui.progress("lidar–encoder time offset") as progress:
                whole = turned(read_recording(path), builder=builder)
                result = with_stored_time_offset(ctx, result, whole, progress, "")
        return result, float(met.turns)
    result, spin = _fit(ctx, strategy, builder)
    return result, spin.turns()


def spin_as_fitted(
    ctx: RunContext, builder: SpinScanBuilder | None
) -> tuple[tuple[int, int | None] | None, Turned]:
    """The stored spin scan as the run's fine-tuning uses it (its returns as ``builder``
    prepared them, when this process took it): cut to what a fit within the budget made while
    scanning saw, as the uninterrupted run, a resumed one and a re-processing cut it. Returns
    (that fit's turns and lines, or None; the scan)."""
    return spin_fitted_later(ctx, builder)()


def _fit(
    ctx: RunContext, strategy: Strategy, builder: SpinScanBuilder | None
) -> tuple[CalibrationResult, Turned]:
    """The pipeline's start and strategy on the stored spin scan (its returns as ``builder``
    prepared them while it was taken, when this process took it), with the time offset when
    there is a second pass, and the scan; the strategy's warnings go to the operator. A scan
    that stopped on a fit within the budget, made by another process (a resumed run), is
    fitted again on the lines that fit saw, as the uninterrupted run and a re-processing do."""
    from calstation.pipeline.stages import Start, fine_tune, platter_start

    met, spin = spin_as_fitted(ctx, builder)
    if met is not None:
        ctx.ui.info(f"  the spin scan stopped on a fit within the budget after {met[0]} "
                    f"turn{'s' if met[0] != 1 else ''}: fine-tuning what that fit saw of its "
                    f"recording")
    with ctx.ui.progress(f"fine-tuning ({strategy.name})") as progress:
        if ctx.recipe.calibration.start == "platter":
            begun = platter_start(ctx.recipe, spin)
        else:
            begun = Start.at(ctx.stored_result("initial"))
        fine = fine_tune(ctx.recipe, strategy, begun, spin, progress)
        if begun.from_platter and fine.start is not None:
            ctx.ui.info(f"  start from the platter: {format_h(fine.start.H.as_dict())} "
                        f"(chord {fine.start.diagnostics['chord']})")
        result = fine.result
        if ctx.recipe.steps.spin_scan.second_pass_rpm is not None:
            result = with_stored_time_offset(ctx, result, spin, progress, "")
    for warning in fine.warnings:
        ctx.ui.warn(warning)
    return result, spin


def with_stored_time_offset(
    ctx: RunContext, result: CalibrationResult, first: Turned, progress: ProgressCallback | None,
    under: str
) -> CalibrationResult:
    """``result`` with the lidar–encoder time offset from the spin scan's ``first`` pass and
    its stored second pass (the pipeline's time-offset stage); ``under`` says which H, for the
    operator."""
    from calstation.pipeline.stages import time_offset
    from calstation.recordings.reader import read_recording

    out = time_offset(ctx.recipe, result, first, read_recording(ctx.artifact_path(SECOND_PASS)),
                      progress)
    ctx.ui.info(
        f"  lidar–encoder time offset{under}: "
        f"{display.with_sigma('time_offset', out.encoder_latency_s, out.sigma_encoder_latency_s)}"
    )
    return out
