"""The fine-tuning strategy interface and calstation's two built-in strategies.

A strategy refines a starting H from the spin scan of one fixture. Plugins add strategies through
the ``calstation_register_cost_strategies`` hook (see :mod:`calstation.plugins.hookspecs`); the
built-ins register the same way (:mod:`calstation.plugins.builtin.strategies`).

Beside the interface, :func:`run_strategy`: a strategy run with its result checked, the way
every caller runs one (the calibration pipeline, :mod:`calstation.pipeline`, and the plugin
author's tests). The strategies hand the recipe's sections to the engine
(:mod:`calstation.engine`), which knows no recipe.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from dataclasses import replace
from typing import TYPE_CHECKING, Protocol, TypeVar, overload, runtime_checkable

from pydantic import BaseModel, ConfigDict, ValidationError

from calstation.errors import FineTuningError, PluginError
from calstation.recipes import Recipe, ShapeOptions

if TYPE_CHECKING:  # NumPy loads when a strategy runs: `recipes validate` checks options only
    from calstation.engine.frames import Extrinsics
    from calstation.engine.result import CalibrationResult
    from calstation.engine.spinscan import SpinScan
    from calstation.recordings.recorded import Recording

Progress = Callable[[str, float], None]
"""``progress(message, fraction)`` with fraction in [0, 1]."""


@runtime_checkable
class Strategy(Protocol):
    """A fine-tuning strategy.

    - ``name``: what recipes write in ``calibration.strategy`` and ``--strategy`` accepts;
    - ``fixture``: which fixture's spin scan it needs, ``"spin_target"`` or ``"qa_cube"``;
    - ``run``: refine ``start`` from that recording; settings come from ``recipe`` (its own
      section, or ``calibration.options[name]`` for plugins). Raises
      :class:`~calstation.errors.FineTuningError` when the data cannot support a result.

    Optional attributes:

    - ``options_model``: a pydantic model class of the strategy's ``calibration.options[name]``
      mapping. ``calstation recipes validate`` (and every run) checks the recipe's options
      against it and reports each problem with its YAML line; :func:`strategy_options` returns
      the validated options inside ``run``. Without it, options are passed through unchecked.
    - ``result_bounds``: ``(metres, radians)``, how far from ``start`` a result may plausibly
      be (default :data:`DEFAULT_RESULT_BOUNDS`); :func:`run_strategy` rejects results beyond.
    - ``run_prepared(scan, start, recipe, progress)``: the same on a
      :class:`~calstation.engine.spinscan.SpinScan` prepared while it is taken. A strategy with
      it lets the station scan revolution by revolution until the accuracy budget holds
      (``steps.*.max_revolutions``); without it the scan takes its ``revolutions``.
    - ``refit(scan, start, recipe, progress)``: for a spin-target strategy that holds the
      lidar's range model (``calibration.range_model``), the fine-tuning run again from a
      :class:`~calstation.engine.result.CalibrationResult` whose range terms the QA cube set,
      holding them; without it the cube step combines the first result alone.
    """

    name: str
    fixture: str

    def run(
        self,
        recording: Recording,
        start: Extrinsics,
        recipe: Recipe,
        progress: Progress | None = None,
    ) -> CalibrationResult:
        """Refine ``start`` (frame convention of DESIGN §2) from ``recording``."""
        ...


# The optional capabilities of a strategy, each found with ``isinstance`` (the attribute is
# there; what it holds is checked where it is used).
@runtime_checkable
class HasOptionsModel(Protocol):
    """A strategy that declares ``options_model``, the pydantic model of its options."""

    options_model: type[BaseModel]


@runtime_checkable
class HasResultBounds(Protocol):
    """A strategy that declares ``result_bounds``: ``(metres, radians)`` a result may be from
    its start."""

    result_bounds: tuple[float, float]


@runtime_checkable
class RunsPrepared(Protocol):
    """A strategy that fine-tunes a :class:`~calstation.engine.spinscan.SpinScan` prepared
    while it is taken (``run_prepared``): the station may scan until the budget holds."""

    def run_prepared(
        self, scan: SpinScan, start: Extrinsics, recipe: Recipe, progress: Progress | None = None
    ) -> CalibrationResult:
        """:meth:`Strategy.run` on a prepared scan."""
        ...


@runtime_checkable
class Refits(Protocol):
    """A spin-target strategy that runs again from a combined estimate holding its range terms
    (``refit``): the cube step lets the spin target follow the range model the cube set."""

    def refit(
        self, scan: SpinScan, start: CalibrationResult, recipe: Recipe,
        progress: Progress | None = None,
    ) -> CalibrationResult:
        """The fine-tuning again from ``start``, holding its range terms."""
        ...


class NoOptions(BaseModel):
    """The options model of a strategy that takes none: any key is an error."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class PeriodicityStrategy:
    """Periodicity-constrained fine-tuning on the spin target (paper §III-B-2); its settings are
    ``calibration.periodicity``, so ``calibration.options.periodicity`` takes no key."""

    name = "periodicity"
    fixture = "spin_target"
    options_model = NoOptions

    def run(
        self,
        recording: Recording,
        start: Extrinsics,
        recipe: Recipe,
        progress: Progress | None = None,
    ) -> CalibrationResult:
        """See :func:`calstation.engine.periodicity.periodicity_fine_tune`."""
        from calstation.engine.periodicity import periodicity_fine_tune

        return periodicity_fine_tune(
            recording,
            start,
            recipe.calibration.periodicity,
            platter_radius=recipe.fixtures.platter.radius,
            progress=progress,
            range_model=recipe.calibration.range_model,
            incidence=recipe.calibration.incidence_bias == "estimate",
            encoder=recipe.station.encoder.accuracy_deg > 0,
        )

    def run_prepared(
        self, scan: SpinScan, start: Extrinsics, recipe: Recipe, progress: Progress | None = None
    ) -> CalibrationResult:
        """:meth:`run` on a scan prepared while it is taken."""
        from calstation.engine.periodicity import periodicity_fine_tune_scan

        return periodicity_fine_tune_scan(
            scan, start, recipe.calibration.periodicity,
            platter_radius=recipe.fixtures.platter.radius, progress=progress,
            range_model=recipe.calibration.range_model,
            incidence=recipe.calibration.incidence_bias == "estimate",
            encoder=recipe.station.encoder.accuracy_deg > 0,
        )


    def refit(
        self, scan: SpinScan, start: CalibrationResult, recipe: Recipe,
        progress: Progress | None = None,
    ) -> CalibrationResult:
        """The fine-tuning run again from ``start`` (a combined estimate), its last stage only,
        holding ``start``'s range terms and ty: how the cube step lets the spin target follow
        the range model the cube set (:func:`calstation.engine.joint.
        combine_range_with_cube_scan`)."""
        from calstation.engine.periodicity import periodicity_fine_tune_scan

        return periodicity_fine_tune_scan(
            scan, start.H, recipe.calibration.periodicity,
            platter_radius=recipe.fixtures.platter.radius, progress=progress, warm=True,
            range_model=recipe.calibration.range_model,
            incidence=recipe.calibration.incidence_bias == "estimate",
            encoder=recipe.station.encoder.accuracy_deg > 0,
            start_range=start.range_model,
        )


class ShapeStrategy:
    """Shape-constrained fine-tuning on the QA cube (paper §III-B-1).

    ``calibration.options.shape``: ``box`` — ``upright`` (default) or ``minimal`` (the
    paper's box); ``estimate_ry`` — estimate ry too (default true; false holds it at its
    start); ``coarse`` — align a far start first with the coarse periodicity stages on the cube
    scan (default true); ``known_size`` — finish with a cube of the recipe's edge fitted to its
    faces (default true).
    """

    name = "shape"
    fixture = "qa_cube"
    options_model = ShapeOptions

    def run(
        self,
        recording: Recording,
        start: Extrinsics,
        recipe: Recipe,
        progress: Progress | None = None,
    ) -> CalibrationResult:
        """See :func:`calstation.engine.shape.shape_fine_tune`."""
        from calstation.engine.shape import shape_fine_tune

        options = strategy_options(self, recipe, ShapeOptions)
        return shape_fine_tune(
            recording,
            start,
            recipe.fixtures.qa_cube,
            recipe.calibration.shape,
            platter_radius=recipe.fixtures.platter.radius,
            box=options.box,
            estimate_ry=options.estimate_ry,
            coarse=options.coarse,
            known_size=options.known_size,
            progress=progress,
            range_model=recipe.calibration.range_model,
            incidence=recipe.calibration.incidence_bias == "estimate",
            encoder=recipe.station.encoder.accuracy_deg > 0,
        )

    def run_prepared(
        self, scan: SpinScan, start: Extrinsics, recipe: Recipe, progress: Progress | None = None
    ) -> CalibrationResult:
        """:meth:`run` on a scan prepared while it is taken."""
        from calstation.engine.shape import shape_fine_tune_points

        options = strategy_options(self, recipe, ShapeOptions)
        return shape_fine_tune_points(
            scan.p_L, scan.phi, start, recipe.fixtures.qa_cube, recipe.calibration.shape,
            platter_radius=recipe.fixtures.platter.radius, box=options.box,
            estimate_ry=options.estimate_ry, coarse=options.coarse,
            known_size=options.known_size, progress=progress, scan=scan,
            range_model=recipe.calibration.range_model,
            incidence=recipe.calibration.incidence_bias == "estimate",
            encoder=recipe.station.encoder.accuracy_deg > 0,
        )


BUILTIN_STRATEGIES: tuple[Strategy, ...] = (PeriodicityStrategy(), ShapeStrategy())
"""The strategies calstation registers itself."""


# --- options -----------------------------------------------------------------------------------
M = TypeVar("M", bound=BaseModel)

OptionProblem = tuple[tuple[int | str, ...], str]
"""A problem in a recipe's strategy options: the field path in the recipe and the message."""


def options_model_of(strategy: object) -> type[BaseModel] | None:
    """The strategy's ``options_model`` (a pydantic model class), None when it declares none.

    Raises :class:`PluginError` when the attribute is there but is not a pydantic model class.
    """
    if not isinstance(strategy, HasOptionsModel):
        return None
    model: object = strategy.options_model
    if model is None:
        return None
    if not (isinstance(model, type) and issubclass(model, BaseModel)):
        raise PluginError(
            f"strategy {getattr(strategy, 'name', strategy)!r}: options_model must be a pydantic "
            f"BaseModel subclass, got {model!r}"
        )
    return model


def option_problems(
    name: str, model: type[BaseModel] | None, options: Mapping[str, object]
) -> list[OptionProblem]:
    """Problems of ``calibration.options[name]`` against ``model`` (none when it is None)."""
    if model is None:
        return []
    try:
        model.model_validate(dict(options))
    except ValidationError as exc:
        return [
            (
                ("calibration", "options", name, *err["loc"]),
                "unknown option" if err["type"] == "extra_forbidden" else err["msg"],
            )
            for err in exc.errors()
        ]
    return []


@overload
def strategy_options(strategy: Strategy, recipe: Recipe, model: type[M]) -> M: ...


@overload
def strategy_options(
    strategy: Strategy, recipe: Recipe, model: None = None
) -> BaseModel | dict[str, object]: ...


def strategy_options(
    strategy: Strategy, recipe: Recipe, model: type[M] | None = None
) -> BaseModel | dict[str, object]:
    """The validated ``calibration.options[strategy.name]`` of ``recipe``.

    An instance of ``model`` when given (the strategy's own ``options_model``, typed), else of
    the strategy's ``options_model``; the raw mapping when the strategy declares no model. A
    problem raises :class:`~calstation.errors.FineTuningError` naming the option.
    """
    raw: dict[str, object] = dict(recipe.calibration.options.get(strategy.name, {}))
    cls = model or options_model_of(strategy)
    if cls is None:
        return raw
    problems = option_problems(strategy.name, cls, raw)
    if problems:
        loc, msg = problems[0]
        raise FineTuningError(f"{'.'.join(str(x) for x in loc)}: {msg}")
    return cls.model_validate(raw)


def recipe_option_problems(
    recipe: Recipe, strategies: Mapping[str, Strategy]
) -> list[OptionProblem]:
    """Every problem of the recipe's ``calibration.options`` against the registered
    ``strategies`` (by name) that declare an ``options_model``; unknown strategy names are left
    to the caller."""
    problems: list[OptionProblem] = []
    for name, options in recipe.calibration.options.items():
        if name in strategies:
            problems += option_problems(name, options_model_of(strategies[name]), options)
    return problems


# --- guarded execution -------------------------------------------------------------------------
DEFAULT_RESULT_BOUNDS: tuple[float, float] = (0.3, math.radians(10.0))
"""How far (metres, radians per parameter) a fine-tuned H may be from its start.

Wide enough for the paper's set-B starts (±200 mm, ±2°) to converge, narrow enough to catch a
result that is no calibration of this station (a plugin's ry of 90°, tx of 760 mm)."""


def check_result(
    strategy: Strategy, result: object, start: Extrinsics
) -> tuple[CalibrationResult, list[str]]:
    """Validate what a strategy's ``run`` returned; returns (result, warnings).

    Errors (:class:`FineTuningError`, naming the strategy, parameter, start and result): not a
    :class:`CalibrationResult`, a non-finite parameter, a parameter further from ``start`` than
    the strategy's ``result_bounds``. Warnings: a non-finite cost, rx moved off its start (rx is
    the gauge, DESIGN §2), a result labelled with another strategy's name.
    """
    from calstation.engine.frames import PARAMETER_NAMES
    from calstation.engine.result import CalibrationResult

    name = getattr(strategy, "name", "?")
    if not isinstance(result, CalibrationResult):
        raise FineTuningError(
            f"strategy {name!r} returned {type(result).__name__}, not a CalibrationResult"
        )
    bound_t, bound_r = (strategy.result_bounds if isinstance(strategy, HasResultBounds)
                        else DEFAULT_RESULT_BOUNDS)
    new, old = result.H.as_dict(), start.as_dict()
    warnings: list[str] = []
    for p in PARAMETER_NAMES:
        value, begin = float(new[p]), float(old[p])
        if not math.isfinite(value):
            raise FineTuningError(f"strategy {name!r} returned {p} = {value}: not a number")
        rotation = p.startswith("r")
        limit = bound_r if rotation else bound_t
        if abs(value - begin) > limit:
            raise FineTuningError(
                f"strategy {name!r} returned {p} = {_shown(p, value)}, "
                f"{_shown(p, value - begin)} from its start {_shown(p, begin)}; results further "
                f"than {_shown(p, limit)} from the start are rejected as implausible"
            )
    if abs(new["rx"] - old["rx"]) > 1e-12:
        warnings.append(
            f"strategy {name!r} moved rx from {_shown('rx', old['rx'])} to "
            f"{_shown('rx', new['rx'])}; rx is the encoder-zero gauge and is normally held"
        )
    if not math.isfinite(float(result.cost)):
        warnings.append(f"strategy {name!r} reported a cost of {result.cost}")
    if result.strategy != name:
        warnings.append(f"strategy {name!r} labelled its result {result.strategy!r}")
    return result, warnings


def _shown(p: str, v: float) -> str:
    return f"{math.degrees(v):.3f}°" if p.startswith("r") else f"{v * 1e3:.2f} mm"


def run_strategy(
    strategy: Strategy,
    recording: Recording | None,
    start: Extrinsics,
    recipe: Recipe,
    progress: Progress | None = None,
    *,
    prepared: SpinScan | None = None,
) -> tuple[CalibrationResult, list[str]]:
    """Run ``strategy`` and check its result (:func:`check_result`); returns (result, warnings).

    ``prepared``: the recording's returns already prepared
    (:func:`calstation.engine.spinscan.from_recording`, or while the scan was taken): a strategy
    with ``run_prepared`` then fine-tunes them instead of preparing the recording again (the
    same result). ``recording`` may be None for a scan still being taken, whose ``prepared``
    lines only such a strategy can fine-tune. The wall-clock time of the run is stored as
    ``timings["total"]`` when the strategy did not report a finite one itself, so no caller ever
    prints a missing time.
    """
    t0 = time.perf_counter()
    result = strategy_result(strategy, recording, start, recipe, progress, prepared=prepared)
    elapsed = time.perf_counter() - t0
    result, warnings = check_result(strategy, result, start)
    total = result.timings.get("total")
    if total is None or not math.isfinite(float(total)):
        result = replace(result, timings={**result.timings, "total": elapsed})
    return result, warnings


def strategy_result(
    strategy: Strategy,
    recording: Recording | None,
    start: Extrinsics,
    recipe: Recipe,
    progress: Progress | None = None,
    *,
    prepared: SpinScan | None = None,
) -> CalibrationResult:
    """The strategy's own result, unchecked (the bench measures what a strategy returns): on
    ``prepared`` with ``run_prepared`` when both are there (its errors naming the recording as
    ``run``'s do), else on ``recording``. :func:`run_strategy` checks it."""
    if prepared is not None and isinstance(strategy, RunsPrepared):
        try:
            return strategy.run_prepared(prepared, start, recipe, progress)
        except FineTuningError as exc:
            if recording is None:
                raise
            raise FineTuningError(f"{recording.path}: {exc}") from None
    if recording is None and prepared is not None:
        raise FineTuningError(
            f"strategy {getattr(strategy, 'name', strategy)!r} cannot fine-tune a scan still "
            "being taken (it has no run_prepared)"
        )
    # the recording as the caller gave it (a strategy's own test may pass none at all)
    run: Callable[..., CalibrationResult] = strategy.run
    return run(recording, start, recipe, progress)
