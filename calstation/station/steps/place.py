"""The placement steps: the operator places a fixture (the L-target, the spin target the
strategy needs, the QA cube) and confirms; unattended, the ``calstation_fixture_placed`` hook
places it (the simulator puts it into its scene)."""

from __future__ import annotations

from calstation import plugins
from calstation.display import fixture_name
from calstation.errors import AbortRun
from calstation.station.context import RunContext
from calstation.station.operator import placement_prompt
from calstation.station.outcome import StepOutcome


def place(ctx: RunContext, fixture: str) -> StepOutcome:
    """Ask the operator to place ``fixture`` (a ``fixtures`` key of the recipe) and tell the
    plugins it is placed; :class:`AbortRun` when the operator aborts instead."""
    geometry = getattr(ctx.recipe.fixtures, fixture)
    if not ctx.ui.confirm_fixture(fixture, placement_prompt(fixture, geometry)):
        raise AbortRun(f"aborted by the operator while placing the {fixture_name(fixture)}")
    plugins.fixture_placed(ctx.hardware().context, fixture, geometry)
    return StepOutcome({"fixture": fixture, "kind": geometry.kind,
                        "unattended": ctx.ui.unattended})


class PlaceStaticTarget:
    """The operator places the L-target for the static scan."""

    name = "place_static_target"

    def run(self, ctx: RunContext, step_id: int) -> StepOutcome:
        """Place the ``static_target``."""
        return place(ctx, "static_target")


class PlaceSpinTarget:
    """The operator places the fixture the strategy fine-tunes on (``spin_target`` for
    periodicity, ``qa_cube`` for shape)."""

    name = "place_spin_target"

    def run(self, ctx: RunContext, step_id: int) -> StepOutcome:
        """Place the strategy's fixture."""
        return place(ctx, ctx.strategy().fixture)


class PlaceQaCube:
    """The operator places the QA cube for the cube scan."""

    name = "place_qa_cube"

    def run(self, ctx: RunContext, step_id: int) -> StepOutcome:
        """Place the ``qa_cube``."""
        return place(ctx, "qa_cube")
