"""The fine-tuning strategy interface and calstation's two built-in strategies.

A strategy refines a starting H from the spin scan of one fixture. Plugins add strategies through
the ``calstation_register_cost_strategies`` hook (see :mod:`calstation.hookspecs`); the built-ins
register the same way (:mod:`calstation.builtin_plugins.strategies`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

from pydantic import BaseModel, ValidationError

from .errors import FineTuningError
from .frames import Extrinsics
from .recipe import PeriodicityOptions, Recipe, ShapeOptions
from .result import CalibrationResult

if TYPE_CHECKING:
    from .recording import Recording

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

    A strategy may also declare ``options_model``: a pydantic model of its
    ``calibration.options.<name>`` section (``extra="forbid"`` makes unknown keys errors).
    ``calstation recipes validate`` and every run check the recipe's options against it, with
    the field and line of each problem; :func:`strategy_options` gives the validated model.
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


class PeriodicityStrategy:
    """Periodicity-constrained fine-tuning on the spin target (paper §III-B-2)."""

    name = "periodicity"
    fixture = "spin_target"
    options_model = PeriodicityOptions

    def run(
        self,
        recording: Recording,
        start: Extrinsics,
        recipe: Recipe,
        progress: Progress | None = None,
    ) -> CalibrationResult:
        """See :func:`calstation.periodicity.periodicity_fine_tune`."""
        from .periodicity import periodicity_fine_tune

        return periodicity_fine_tune(
            recording,
            start,
            recipe.calibration.periodicity,
            platter_radius=recipe.fixtures.platter.radius,
            progress=progress,
        )


class ShapeStrategy:
    """Shape-constrained fine-tuning on the QA cube (paper §III-B-1).

    ``calibration.options.shape``: ``box`` — ``upright`` (default) or ``minimal`` (the
    paper's box); ``estimate_ry`` — estimate ry too (default true; false holds it at its
    start); ``coarse`` — align a far start first with the coarse periodicity stages on the cube
    scan (default true).
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
        """See :func:`calstation.shape.shape_fine_tune`."""
        from .shape import shape_fine_tune

        options = strategy_options(self, recipe)
        assert isinstance(options, ShapeOptions)
        return shape_fine_tune(
            recording,
            start,
            recipe.fixtures.qa_cube,
            recipe.calibration.shape,
            platter_radius=recipe.fixtures.platter.radius,
            box=options.box,
            estimate_ry=options.estimate_ry,
            coarse=options.coarse,
            progress=progress,
        )


BUILTIN_STRATEGIES: tuple[Strategy, ...] = (PeriodicityStrategy(), ShapeStrategy())
"""The strategies calstation registers itself."""


def strategy_options(strategy: Strategy, recipe: Recipe) -> BaseModel | dict[str, Any]:
    """The strategy's ``calibration.options.<name>``, validated by its ``options_model`` when it
    declares one (else the plain mapping). FineTuningError names the field of a problem."""
    raw = recipe.calibration.options.get(strategy.name) or {}
    model: type[BaseModel] | None = getattr(strategy, "options_model", None)
    if model is None:
        return dict(raw)
    try:
        return model.model_validate(raw)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(x) for x in first["loc"])
        raise FineTuningError(
            f"calibration.options.{strategy.name}.{where}: {first['msg']}"
        ) from None


def get_strategy(name: str) -> Strategy:
    """The registered strategy ``name`` (built-in or plugin); PluginError lists the known ones."""
    from . import plugins

    found: Strategy = plugins.strategy(name)
    return found
