"""The steps of a run, one small class per step, each in its own module.

A step has a ``name`` (its state in the station's machine) and ``run(ctx, step_id)``, which does
the step's work on the run's :class:`~calstation.station.context.RunContext` and returns a
:class:`~calstation.station.outcome.StepOutcome`: what to store. Failing is raising (a
:class:`~calstation.errors.CalstationError` whose message the operator reads) or, for a QA
verdict, an outcome with ``failure``. A step never decides its own retry, never stores its
outcome and never moves the machine: :class:`calstation.station.machine.Station` does.

The workflow (DESIGN §1)::

    preflight → place_static_target → static_scan (+ initial calibration)
              → place_spin_target → spin_scan → fine_tune
              → place_qa_cube → cube_scan (+ cube check) → report
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Protocol

from calstation.recipes import Recipe
from calstation.station.context import RunContext
from calstation.station.outcome import StepOutcome
from calstation.station.steps.cube_scan import CubeScan
from calstation.station.steps.fine_tune import FineTune
from calstation.station.steps.place import PlaceQaCube, PlaceSpinTarget, PlaceStaticTarget
from calstation.station.steps.preflight import Preflight
from calstation.station.steps.report import Report
from calstation.station.steps.spin_scan import SpinScan
from calstation.station.steps.static_scan import StaticScan

STEPS: tuple[str, ...] = (
    "preflight",
    "place_static_target",
    "static_scan",
    "place_spin_target",
    "spin_scan",
    "fine_tune",
    "place_qa_cube",
    "cube_scan",
    "report",
)
"""The steps of a run, in order (each is a state of the machine)."""

TARGETLESS_DROPS = ("place_static_target", "static_scan")
"""The steps a run without the L-target leaves out (``calibration.start: platter``)."""


class Step(Protocol):
    """One step of a run."""

    name: str
    """The step's name: its state in the machine, its ``step`` rows, its events."""

    def run(self, ctx: RunContext, step_id: int) -> StepOutcome:
        """Do the step's work for its attempt ``step_id`` (the ``step`` row); what to store."""
        ...


REGISTRY: Mapping[str, Step] = {
    step.name: step
    for step in (
        Preflight(), PlaceStaticTarget(), StaticScan(), PlaceSpinTarget(), SpinScan(),
        FineTune(), PlaceQaCube(), CubeScan(), Report(),
    )
}
"""Each step of :data:`STEPS` by its name."""


def run_steps(recipe: Recipe) -> tuple[str, ...]:
    """The steps a run of ``recipe`` takes, in order: :data:`STEPS`, without the L-target's
    placement and static scan when the fine-tuning starts from the platter."""
    if recipe.calibration.start == "platter":
        return tuple(s for s in STEPS if s not in TARGETLESS_DROPS)
    return STEPS
