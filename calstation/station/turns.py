"""Scanning until the accuracy budget holds: one more revolution at a time.

A spin scan turns its ``revolutions`` first. From then on, each time another whole revolution
has been recorded, :class:`TurnByTurn` fine-tunes on the data so far — the lines already prepared
as they arrived (:meth:`calstation.engine.spinscan.SpinScanBuilder.so_far`), in a background
thread while the scan goes on — and predicts the reconstruction error. The scan stops as soon
as a prediction is within ``calibration.accuracy.max_error``, or at ``max_revolutions`` turns, or
after ``max_duration_s`` seconds of scanning. Each prediction is published to the operator
(the ``accuracy`` event, and a line on the console) as it arrives, so the operator sees the
error falling.

The recording holds every turn. The step that follows takes the fit that met the budget, on the
turns it saw — fits see each turn's data as the line completing it arrived, and are taken in
order, so that a run's outcome does not depend on how fast they ran — and fine-tunes every whole
turn of the recording when none met it.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import replace
from typing import TYPE_CHECKING

from calstation import display
from calstation.engine.accuracy import PredictedError
from calstation.engine.result import CalibrationResult
from calstation.engine.spinscan import SpinScan, SpinScanBuilder
from calstation.errors import FineTuningError
from calstation.plugins.cost_strategies import RunsPrepared
from calstation.recipes import Recipe
from calstation.station.context import RunContext
from calstation.station.operator import Operator, publish
from calstation.station.prepared import FitRecord, ScanTurns, TurnFit, TurnsSummary

if TYPE_CHECKING:
    from calstation.pipeline.scans import Turned
    from calstation.pipeline.stages import CubeChecked

Fit = Callable[[SpinScan], tuple[CalibrationResult, PredictedError, "CubeChecked | None"]]
"""``fit(scan so far)``: the calibration from it, its predicted error, and the cube stage it
made (the cube scan's with the lidar's range model; else None)."""


class NoMoreTurns(Exception):
    """Raised by a :data:`Fit` whose data so far say that more turns would not change the
    outcome (two fixtures that disagree beyond chance): the scan stops, and the step after it
    works on every whole turn of the recording and says why."""


class TurnByTurn:
    """The :class:`~calstation.station.acquisition.MoreTurns` of a scan that goes on while its
    predicted error is above ``budget_m`` (see the module docstring)."""

    def __init__(
        self,
        builder: SpinScanBuilder,
        fit: Fit,
        *,
        budget_m: float,
        max_revolutions: float,
        max_duration_s: float | None,
        ui: Operator,
        scan: str,
        more: Callable[[TurnFit], str | None] | None = None,
        paced: bool = False,
    ) -> None:
        self.builder = builder
        self.fit = fit
        self.more = more
        """why to turn on though a fit is within the budget (None: it is enough)"""
        self.paced = paced
        """the scan's time is simulated (a :class:`~calstation.clock.SimClock`: the lidar runs as
        fast as the host computes it): each turn's fit is taken at the line that completes the
        next turn, waited for there, as if it took one turn of the scan's time; so a simulated
        run does not depend on the host's speed or load, and is the same from the same seed"""
        self.budget_m = budget_m
        self.max_revolutions = max_revolutions
        self.max_duration_s = max_duration_s
        self.ui = ui
        self.scan = scan
        self.fits: list[TurnFit] = []
        self.failures: list[str] = []
        self.met: TurnFit | None = None
        """the first fit within the budget that is enough (``more`` asked for no more): what
        the scan stopped on"""
        self.kept: TurnFit | None = None
        """the last fit within the budget for which ``more`` asked for more turns: what the
        scan stops on when they do not come (the turns run out, the time, or a later fit above
        the budget), so that turning on for ``more`` never costs the budget"""
        self.stopped: str = "turns"
        """why the scan ended: ``budget`` (a fit within it), ``turns``, ``time``, or ``fit``
        (a fit said more turns would not help: :class:`NoMoreTurns`)"""
        self._hopeless = False
        self._pool = ThreadPoolExecutor(1, thread_name_prefix=f"calstation-{scan}-fit")
        self._queued: deque[tuple[int, Future[TurnFit]]] = deque()
        self._asked = 0

    def __call__(self, turns: float, seconds: float) -> bool:
        """Keep turning? (Called by the acquisition after every line, past the first turns.)

        Each whole turn's data is taken at the line that completes it, so what each fit sees
        does not depend on how fast the fits run; they are fitted in order, and the scan stops
        on the first within the budget, whatever turn the scan has reached by then."""
        whole = math.floor(turns + 1e-9)
        # paced: every fit asked at an earlier turn is taken now, at the turn after it
        self._collect(wait=self.paced and whole > self._asked)
        if self.met is not None:
            self.stopped = "budget"
            return False
        if self._hopeless:
            self.stopped = "fit"
            return False
        if self.max_duration_s is not None and seconds >= self.max_duration_s:
            self.stopped = "time"
            return False
        if whole > self._asked:
            scan = self.builder.so_far()
            if scan is not None:
                self._asked = whole
                lines = self.builder.lines_ready
                self._queued.append((whole, self._pool.submit(self._fit, scan, whole, lines)))
        return True

    def _fit(self, scan: SpinScan, turns: int, lines: int) -> TurnFit:
        t0 = time.perf_counter()
        result, predicted, stage = self.fit(scan)
        return TurnFit(turns, result, predicted, time.perf_counter() - t0, lines, stage)

    def _collect(self, wait: bool = False) -> None:
        """Take the finished fits, in the order of their turns, and tell the operator what
        each predicts; the first within the budget is :attr:`met`."""
        while (self._queued and self.met is None and not self._hopeless
               and (wait or self._queued[0][1].done())):
            turns, future = self._queued.popleft()
            exc = future.exception()
            if isinstance(exc, NoMoreTurns):
                self.failures.append(f"after {turns} turns: {exc}")
                self._hopeless = True
                self.ui.info(f"  after {display.count(turns, 'turn')}: {exc}; more turns would "
                             "not change it")
                continue
            if exc is not None:
                # the data so far may not support a fit (too little of the target yet): the
                # scan goes on; the step after it fine-tunes the whole recording and reports
                self.failures.append(f"after {turns} turns: {exc}")
                continue
            fit = future.result()
            self.fits.append(fit)
            within = fit.predicted.max_m <= self.budget_m
            more = None if not within or self.more is None else self.more(fit)
            self._announce(fit, more)
            if within and more is None:
                self.met = fit
            elif within:
                self.kept = fit
            elif self.kept is not None:  # above the budget after turning on for ``more``
                self._end_on_kept()

    def _end_on_kept(self) -> None:
        """The scan stops on :attr:`kept`, the last fit within the budget."""
        assert self.kept is not None
        self.ui.info(f"  the scan ends on the fit after "
                     f"{display.count(self.kept.turns, 'turn')}, within the budget")
        self.met = self.kept

    def _announce(self, fit: TurnFit, more: str | None) -> None:
        publish(self.ui, "accuracy", scan=self.scan, turns=fit.turns,
                predicted_error_m=fit.predicted.max_m, budget_m=self.budget_m,
                sigma=dict(fit.result.sigma), fit_s=fit.seconds, more=more)
        verdict = "within" if fit.predicted.max_m <= self.budget_m else "above"
        self.ui.info(f"  after {display.count(fit.turns, 'turn')}: predicted error "
                     f"{display.number('predicted_error', fit.predicted.max_m)}, {verdict} the "
                     f"budget of {display.number('predicted_error', self.budget_m)} "
                     f"({display.duration(fit.seconds)} to fit)"
                     + ("" if more is None else f"; turning on: {more}"))

    def close(self, whole_turns: int) -> ScanTurns:
        """The scan has ended with ``whole_turns`` whole revolutions. A scan stopped by the
        budget keeps the fit that met it (the turns it saw; those scanned while it was computed
        are in the recording but not in the result, so a run's outcome does not depend on how
        fast the fits ran). Otherwise the fits still queued are finished, in order; when one of
        them meets the budget it is kept, else the step after the scan fine-tunes every whole
        turn of the recording."""
        if self.met is None:
            self._collect(wait=True)
            if self.met is None and not self._hopeless and self.kept is not None:
                self._end_on_kept()
            if self.met is not None:
                self.stopped = "budget"
            elif self._hopeless:
                self.stopped = "fit"
        # a later turn's fit already under way is not waited for: the step after the scan
        # does not use it, and its thread ends with it
        self._pool.shutdown(wait=False, cancel_futures=True)
        return ScanTurns(self.met, {**self.summary(), "whole_turns": whole_turns})

    def summary(self) -> TurnsSummary:
        """What the scan did, for the step's stored result."""
        out: TurnsSummary = {
            "stopped": self.stopped,
            "budget_m": self.budget_m,
            "max_revolutions": self.max_revolutions,
            "fits": [FitRecord(turns=f.turns, predicted_error_m=f.predicted.max_m,
                               seconds=f.seconds, lines=f.lines) for f in self.fits],
            "failed_fits": list(self.failures),
        }
        if self.met is not None:
            out["met_turns"] = self.met.turns
        return out


def simulated_time(ctx: RunContext) -> bool:
    """Whether the run's scans take simulated time (its drivers' clock is a
    :class:`~calstation.clock.SimClock`): their turn-by-turn fits are then paced
    (:attr:`TurnByTurn.paced`)."""
    from calstation.clock import SimClock

    return isinstance(ctx.hardware().clock, SimClock)


def turns_fitted(summary: TurnsSummary | None) -> tuple[int, int | None] | None:
    """(the whole turns, the recording's first lines) of the fit a scan stopped on, from its
    stored ``turn_by_turn`` :meth:`TurnByTurn.summary` (its ``met_turns``; a summary stored
    before it was kept ends its fits with that one; the lines are None in a summary stored
    without them); None when the scan did not stop on the budget (every whole turn of its
    recording counts)."""
    if summary is None:
        return None
    fits = summary.get("fits") or []
    if summary.get("stopped") != "budget" or not fits:
        return None
    met = summary.get("met_turns")
    fit = next((f for f in fits if f["turns"] == met), fits[-1])
    lines = fit.get("lines")
    return int(fit["turns"]), None if lines is None else int(lines)


def more_turns(ctx: RunContext, scan: str) -> Callable[[SpinScanBuilder], TurnByTurn] | None:
    """How the spin scan ``scan`` (``spin_scan``) goes on until the budget holds, or None when
    it takes exactly its ``revolutions``: a recipe whose ``max_revolutions`` adds none, a
    strategy that cannot fine-tune a scan under way (no ``run_prepared``), or a start that is
    not known before the scan (the platter's chord is found in the scan itself)."""
    from calstation.recipes.validation import most_turns

    cfg = getattr(ctx.recipe.steps, scan)
    strategy = ctx.strategy()
    most = most_turns(ctx.recipe, scan)
    if (most <= cfg.revolutions or not isinstance(strategy, RunsPrepared)
            or ctx.recipe.calibration.start != "l_target"):
        return None
    from calstation.pipeline.judgement import with_prediction
    from calstation.pipeline.scans import so_far as lines_so_far
    from calstation.pipeline.stages import Start, fine_tune

    begun = Start.at(ctx.stored_result("initial"))
    recipe = ctx.recipe

    def fit(so_far: SpinScan) -> tuple[CalibrationResult, PredictedError, None]:
        result = fine_tune(recipe, strategy, begun, lines_so_far(so_far)).result
        return (*with_prediction(result, recipe), None)

    paced = simulated_time(ctx)

    def controller(builder: SpinScanBuilder) -> TurnByTurn:
        return TurnByTurn(builder, fit, budget_m=recipe.calibration.accuracy.max_error,
                          max_revolutions=most, max_duration_s=cfg.max_duration_s, ui=ctx.ui,
                          scan=scan, paced=paced)

    return controller


def more_cube_turns(ctx: RunContext) -> Callable[[SpinScanBuilder], TurnByTurn] | None:
    """How the cube scan goes on while it is what brings the budget within reach, for a
    spin-target strategy. Each whole revolution, the cube so far is combined with the spin
    target's estimate and the combination's error is predicted: with the lidar's range model,
    the cube's known-size fit with the range terms (:func:`calstation.engine.joint.
    combine_range_with_cube`; the spin target alone leaves them unmeasured, so the cube always
    decides); without it, the cube's side faces' twist combined into ry (:func:`calstation.
    engine.joint.with_cube_ry`), only when the fine calibration is above the budget on its own.
    None when the cube scan takes exactly its ``revolutions``."""
    from calstation.recipes.validation import most_turns

    cfg = ctx.recipe.steps.cube_scan
    most = most_turns(ctx.recipe, "cube_scan")
    if most <= cfg.revolutions or ctx.strategy().fixture != "spin_target":
        return None
    from calstation.pipeline.judgement import with_prediction

    recipe = ctx.recipe
    fine = ctx.stored_result("fine")
    more = None
    if fine.range_offset is not None:
        fit = _range_turn_fit(ctx, fine)
        more = _axis_placed(recipe, most, ctx.ui)
    elif with_prediction(fine, recipe)[1].max_m <= recipe.calibration.accuracy.max_error:
        return None
    else:
        fit = _twist_turn_fit(recipe, fine)

    paced = simulated_time(ctx)

    def controller(builder: SpinScanBuilder) -> TurnByTurn:
        return TurnByTurn(builder, fit, budget_m=recipe.calibration.accuracy.max_error,
                          max_revolutions=most, max_duration_s=cfg.max_duration_s, ui=ctx.ui,
                          scan="cube_scan", more=more, paced=paced)

    return controller


def _axis_placed(
    recipe: Recipe, most: float, ui: Operator
) -> Callable[[TurnFit], str | None] | None:
    """Why the cube scan turns on though the budget holds (the turn-by-turn ``more``): with the
    lidar's range model the cube's size sets where the lidar stands along its rays, and with it
    where H puts the axis; the reconstruction, which applies the range terms, does not feel that
    (the budget), but H used without them does — a URDF. So the scan also turns until the
    axis's σ across it is within ``calibration.accuracy.axis_sigma``, while the turns left can
    bring it there: σ² = floor + c/turns through the last two fits (the floor: what more data
    of the cube cannot reduce — its stated tolerance, the range models' errors). None when the
    limit is unset."""
    from calstation.engine.accuracy import axis_offset_sigma

    limit = recipe.calibration.accuracy.axis_sigma
    if limit is None:
        return None
    seen: list[tuple[int, float]] = []

    def more(fit: TurnFit) -> str | None:
        sigma = axis_offset_sigma(fit.result.H, fit.result.diagnostics.get("covariance"))
        if not sigma > limit:  # NaN: not measured, the budget alone decides
            return None
        shown = (f"the axis's position σ {display.number('axis_offset', sigma)} > "
                 f"{display.number('axis_offset', limit)} (calibration.accuracy.axis_sigma)")
        seen.append((fit.turns, sigma))
        if len(seen) < 2:
            return shown
        (n1, s1), (n2, s2) = seen[-2:]
        c = (s1**2 - s2**2) / (1.0 / n1 - 1.0 / n2)
        floor = s2**2 - c / n2
        needed = c / (limit**2 - floor) if c > 0 and limit**2 > floor else math.inf
        if needed <= most:
            return f"{shown}, about {math.ceil(needed):d} turns bring it within"
        ui.info(f"  {shown}: the cube scan's {most:g} turns would not bring it within "
                + ("(it no longer falls with the turns)" if not c > 0 else
                   f"(it levels off at {display.number('axis_offset', math.sqrt(max(floor, 0)))}: "
                   "what more turns of the cube cannot reduce — its stated tolerance and the "
                   "range model's errors)"))
        return None

    return more


def _range_turn_fit(ctx: RunContext, fine: CalibrationResult) -> Fit:
    """The cube scan's :data:`Fit` with the lidar's range model: the pipeline's cube stage on
    the cube so far (:func:`calstation.pipeline.stages.with_cube`: its known-size fit with the
    range terms combined with the spin target's ``fine``, the spin target's fine-tuning run
    again from the combination, the cube check under it), which the step after the scan takes
    as it is from the fit that met the budget: the operator does not wait for it. Spin target
    and cube that disagree beyond chance stop the scan (:class:`NoMoreTurns`)."""
    from calstation.pipeline.judgement import with_prediction
    from calstation.pipeline.scans import so_far as lines_so_far
    from calstation.pipeline.stages import with_cube

    recipe, strategy = ctx.recipe, ctx.strategy()
    prepared = ctx.prepared.get(ctx.artifact_path("spin"))
    read_spin = spin_fitted_later(ctx, None if prepared is None else prepared.builder)
    spin: list[Turned] = []

    def fit(so_far: SpinScan) -> tuple[CalibrationResult, PredictedError, CubeChecked]:
        if not spin:  # read once, in the fits' thread; its returns with a memo of the fits'
            turned = read_spin()[1]
            spin.append(replace(turned, prepared=replace(turned.prepared, memo={})))
        # a memo of this fit's own: what the stage keeps of the scan so far (its corrected
        # returns, its segmentations) goes with the fit, not with every turn's scan the builder
        # keeps (eight turns at 1000 lines/s held 11 GB)
        cubed = with_cube(recipe, strategy, fine, lines_so_far(replace(so_far, memo={})),
                          spin=spin[0])
        if cubed.result is fine:  # the cube so far could not be fitted: more of it may be
            raise FineTuningError(cubed.ry_failure or "the cube so far could not be fitted")
        if cubed.result.strategy == fine.strategy:  # fitted, and the two disagree beyond chance
            raise NoMoreTurns(cubed.ry_failure)
        return (*with_prediction(cubed.result, recipe), cubed)

    return fit


def spin_fitted_later(
    ctx: RunContext, builder: SpinScanBuilder | None
) -> Callable[[], tuple[tuple[int, int | None] | None, Turned]]:
    """Read, when called, the stored spin scan as the run's fine-tuning uses it (its returns as
    ``builder`` prepared them, when this process took it), cut to what a fit within the budget
    made while scanning saw, as the uninterrupted run, a resumed one and a re-processing cut
    it: (that fit's turns and lines, or None; the scan). What it asks the run's database is
    asked now, so that the reading may be done in another thread."""
    from calstation.pipeline import turned
    from calstation.recordings.reader import read_recording
    from calstation.station.stored import passed_result

    met = turns_fitted(passed_result(ctx.db, ctx.run_id, "spin_scan").get("turn_by_turn"))
    path = ctx.artifact_path("spin")
    return lambda: (met, turned(read_recording(path), fitted=met, builder=builder))


def _twist_turn_fit(recipe: Recipe, fine: CalibrationResult) -> Fit:
    """The cube scan's :data:`Fit` without a range model: the side faces' twist so far combined
    into the spin target's ry."""
    from calstation.engine.cube import check_cube_points
    from calstation.engine.joint import with_cube_ry
    from calstation.pipeline.judgement import with_prediction

    limit = recipe.calibration.max_sigma.ry_deg

    def fit(so_far: SpinScan) -> tuple[CalibrationResult, PredictedError, None]:
        check = check_cube_points(
            so_far.p_L, so_far.phi, fine.H, recipe.fixtures.qa_cube, recipe.qa,
            platter_radius=recipe.fixtures.platter.radius, memo=so_far.memo,
        )
        combined, _ = with_cube_ry(fine, check, None if limit is None else math.radians(limit))
        return (*with_prediction(combined, recipe), None)

    return fit
