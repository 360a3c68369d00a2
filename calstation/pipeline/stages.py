"""The stages of one calibration, each callable on its own (the station runs them one step at a
time): where the fine-tuning starts (:func:`start`: the L-target's initial calibration, or the
platter's chord), the strategy (:func:`fine_tune`), the QA cube's check with ry combined from
its side faces (:func:`with_cube`) and the lidar–encoder time offset (:func:`time_offset`). The
last stage, the judgement, is :mod:`calstation.pipeline.judgement`.

Each stage hands the recipe's sections to the engine (:mod:`calstation.engine`), which knows no
recipe, and reads a spin scan's returns from the preparation the :class:`Turned` carries.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

from calstation.errors import CalstationError, FineTuningError
from calstation.pipeline.scans import Turned
from calstation.plugins.cost_strategies import Refits, Strategy, run_strategy
from calstation.recipes import Recipe

if TYPE_CHECKING:
    from calstation.engine.certificate import Certificate
    from calstation.engine.cube import CubeCheck
    from calstation.engine.frames import Extrinsics
    from calstation.engine.result import CalibrationResult
    from calstation.recordings.recorded import Recording

Progress = Callable[[str, float], None]
"""``progress(message, fraction)`` with fraction in [0, 1]."""


@dataclass(frozen=True)
class Start:
    """Where the fine-tuning starts: ``result``, the L-target's initial calibration (strategy
    ``initial``) or the platter's chord (strategy ``platter``), and ``candidates``, the H the
    strategy runs from (the initial H; or one per sign of tz the chord allows)."""

    result: CalibrationResult
    candidates: tuple[Extrinsics, ...]

    @classmethod
    def at(cls, result: CalibrationResult) -> Start:
        """A start from ``result``'s H alone (the L-target's initial calibration)."""
        return cls(result, (result.H,))

    @property
    def from_platter(self) -> bool:
        """Whether the start came from the platter's chord (no L-target)."""
        return self.result.strategy == "platter"


def initial(recipe: Recipe, static: Recording) -> Start:
    """The initial calibration from the L-target's ``static`` scan (paper §III-A)."""
    from calstation.engine.initial import initial_calibration

    return Start.at(initial_calibration(static, recipe.fixtures.static_target,
                                        recipe.calibration.initial))


def platter_start(recipe: Recipe, spin: Turned) -> Start:
    """The start from the platter's chord in the spin scan (no L-target): tz = 0, and ±|tz|
    when the chord gives one (:mod:`calstation.engine.targetless`)."""
    from calstation.engine.targetless import targetless_start

    if spin.recording is None:
        raise FineTuningError("the platter's chord is found in a whole spin scan, not in the "
                              "lines of one still being taken")
    found = targetless_start(spin.recording, recipe.fixtures.platter,
                             recipe.calibration.initial, prepared=spin.prepared)
    tz = found.diagnostics["tz_candidates_m"]
    return Start(found, tuple(found.H.with_(tz=float(z)) for z in tz))


def start(recipe: Recipe, static: Recording | None, spin: Turned) -> Start:
    """The first stage: :func:`initial` from the L-target's ``static`` scan, or without one
    :func:`platter_start` from ``spin``."""
    return initial(recipe, static) if static is not None else platter_start(recipe, spin)


@dataclass(frozen=True)
class FineTuned:
    """What the strategy made of the spin scan: ``result``, its ``warnings``
    (:func:`~calstation.plugins.cost_strategies.check_result`), and the ``start`` it came from
    (from the platter: the candidate whose result had the lowest cost)."""

    result: CalibrationResult
    warnings: list[str] = field(default_factory=list)
    start: CalibrationResult | None = None


def fine_tune(
    recipe: Recipe, strategy: Strategy, begun: Start, spin: Turned, progress: Progress | None = None
) -> FineTuned:
    """The second stage: ``strategy`` on ``spin`` from ``begun``. From the platter's chord it
    runs from each candidate and keeps the lowest cost (the start, the chord and every
    candidate's cost in ``diagnostics["start"]``); it fails only when every candidate fails."""
    if not begun.from_platter:
        result, warnings = run_strategy(strategy, spin.recording, begun.candidates[0], recipe,
                                        progress, prepared=spin.prepared)
        return FineTuned(result, warnings, begun.result)
    tried: list[tuple[Extrinsics, CalibrationResult, list[str]]] = []
    errors = []
    n = len(begun.candidates)
    for k, H in enumerate(begun.candidates):
        try:
            result, warnings = run_strategy(strategy, spin.recording, H, recipe,
                                            part(progress, k / n, (k + 1) / n),
                                            prepared=spin.prepared)
        except CalstationError as exc:
            errors.append(f"from tz {H.tz * 1e3:+.1f} mm: {exc}")
        else:
            tried.append((H, result, warnings))
    if not tried:
        raise FineTuningError(f"the fine-tuning failed from every start the platter gave: "
                              f"{'; '.join(errors)}")
    H, result, warnings = min(tried, key=lambda t: t[1].cost)
    chosen = replace(begun.result, H=H)
    diagnostics = {**result.diagnostics, "start": {
        "strategy": "platter", "H": H.as_dict(), "chord": chosen.diagnostics["chord"],
        "candidates": [{"tz_m": float(h.tz), "cost": float(r.cost)} for h, r, _ in tried],
        "failed": errors}}
    return FineTuned(replace(result, diagnostics=diagnostics), warnings, chosen)


@dataclass(frozen=True)
class CubeChecked:
    """The QA cube under a calibration: ``result`` (ry combined from the cube's side faces for a
    spin-target strategy, strategy ``<name>+cube``; the calibration itself when nothing was
    combined), the ``check`` under its H, and why ry could not be combined (None: it was, or
    did not need to be)."""

    result: CalibrationResult
    check: CubeCheck
    ry_failure: str | None = None

    def combined(self, before: CalibrationResult) -> bool:
        """Whether the cube's faces changed ``before``."""
        return self.result is not before


def with_cube(
    recipe: Recipe, strategy: Strategy, result: CalibrationResult, cube: Turned,
    progress: Progress | None = None, spin: Turned | None = None,
) -> CubeChecked:
    """The third stage: the QA cube's scan checked under ``result``; for a spin-target strategy
    its side faces' twist combined into ry first (:func:`calstation.engine.joint.
    combine_with_cube_scan`, gated on ``calibration.max_sigma.ry_deg``), or with the lidar's
    range model, the cube's known-size fit combined with ``result`` — the strategy run again on
    ``spin`` from the combination when it can (its ``refit``). A cube scan still being taken
    (no recording) is checked on its lines so far: the cube scan's fits while it turns, whose
    lines are those its recording is cut to after."""
    from calstation.engine.cube import check_cube
    from calstation.engine.joint import combine_with_cube_scan

    rc = recipe
    if strategy.fixture != "spin_target":
        from calstation.engine.joint import with_encoder_error

        result = with_encoder_error(result, math.radians(rc.station.encoder.accuracy_deg))
        result, failure = certified(rc, result)
        check = check_cube(cube.recording, result.H, rc.fixtures.qa_cube, rc.qa,
                           platter_radius=rc.fixtures.platter.radius, prepared=cube.prepared,
                           range_model=result.range_model)
        return CubeChecked(result, check, failure)
    limit = rc.calibration.max_sigma.ry_deg
    refit = strategy.refit if isinstance(strategy, Refits) else None
    combined, check, failure = combine_with_cube_scan(
        result, cube.recording, rc.fixtures.qa_cube, rc.qa,
        platter_radius=rc.fixtures.platter.radius,
        max_sigma_ry=None if limit is None else math.radians(limit),
        progress=progress, prepared=cube.prepared,
        refit=None if spin is None or refit is None else (
            lambda start: refit(spin.prepared, start, rc)),
        certificate=certificate(rc),
        encoder_accuracy=math.radians(rc.station.encoder.accuracy_deg),
    )
    return CubeChecked(combined, check, failure)


def certificate(recipe: Recipe) -> Certificate | None:
    """The lidar's range offset certificate of ``recipe`` (``calibration.
    range_offset_certificate``), or None."""
    from calstation.engine.certificate import Certificate

    said = recipe.calibration.range_offset_certificate
    return None if said is None else Certificate(said.offset, said.sigma)


def certified(recipe: Recipe, result: CalibrationResult) -> tuple[CalibrationResult, str | None]:
    """``result`` of a strategy that measured the range offset itself (the cube's), with the
    recipe's certificate combined into it (:func:`calstation.engine.certificate.
    with_certificate`): (the result, why it disagrees or None). Once: a result already combined
    is returned as it is."""
    from calstation.engine.certificate import with_certificate

    if "certificate" in result.diagnostics:
        return result, None
    return with_certificate(result, certificate(recipe))


def time_offset(
    recipe: Recipe, result: CalibrationResult, spin: Turned, second: Recording,
    progress: Progress | None = None,
) -> CalibrationResult:
    """The fourth stage: ``result`` with the lidar–encoder time offset from the spin scan's two
    passes under its H (the whole first pass, and the ``second``)."""
    from calstation.engine.timeoffset import with_time_offset

    first, prepared = spin.complete()
    if first is None:
        raise FineTuningError("the time offset needs the spin scan's whole first pass")
    return with_time_offset(result, first, second, recipe.fixtures.platter.radius, progress,
                            prepared_first=prepared)


def part(progress: Progress | None, low: float, high: float) -> Progress | None:
    """``progress`` for the share [low, high] of a longer task (None stays None)."""
    if progress is None:
        return None
    say = progress

    def scaled(message: str, fraction: float) -> None:
        say(message, low + (high - low) * max(0.0, min(1.0, fraction)))

    return scaled
