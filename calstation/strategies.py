"""The fine-tuning strategy interface and calstation's two built-in strategies.

A strategy refines a starting H from the spin scan of one fixture. Plugins add strategies through
the ``calstation_register_cost_strategies`` hook (see :mod:`calstation.hookspecs`); the built-ins
register the same way (:mod:`calstation.builtin_plugins.strategies`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

from .errors import FineTuningError
from .frames import Extrinsics
from .recipe import Recipe
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


def _platter_radius(recipe: Recipe) -> float:
    return recipe.fixtures.platter.radius


class PeriodicityStrategy:
    """Periodicity-constrained fine-tuning on the spin target (paper §III-B-2)."""

    name = "periodicity"
    fixture = "spin_target"

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
            platter_radius=_platter_radius(recipe),
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

    def run(
        self,
        recording: Recording,
        start: Extrinsics,
        recipe: Recipe,
        progress: Progress | None = None,
    ) -> CalibrationResult:
        """See :func:`calstation.shape.shape_fine_tune`."""
        from .shape import shape_fine_tune

        options: dict[str, Any] = dict(recipe.calibration.options.get("shape", {}))
        box = str(options.pop("box", "upright"))
        estimate_ry = bool(options.pop("estimate_ry", True))
        coarse = bool(options.pop("coarse", True))
        if box not in ("upright", "minimal"):
            raise FineTuningError(
                f"calibration.options.shape.box must be 'upright' or 'minimal', got {box!r}"
            )
        if options:
            raise FineTuningError(
                f"calibration.options.shape: unknown keys {', '.join(sorted(options))} "
                "(known: box, estimate_ry, coarse)"
            )
        return shape_fine_tune(
            recording,
            start,
            recipe.fixtures.qa_cube,
            recipe.calibration.shape,
            platter_radius=_platter_radius(recipe),
            box=box,
            estimate_ry=estimate_ry,
            coarse=coarse,
            progress=progress,
        )


BUILTIN_STRATEGIES: tuple[Strategy, ...] = (PeriodicityStrategy(), ShapeStrategy())
"""The strategies calstation registers itself."""


def get_strategy(name: str) -> Strategy:
    """The registered strategy ``name`` (built-in or plugin); PluginError lists the known ones."""
    from . import plugins

    found: Strategy = plugins.strategy(name)
    return found
