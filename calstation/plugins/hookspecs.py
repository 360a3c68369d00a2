"""Every hook calstation calls, in one place. Plugins implement them with ``@hookimpl``.

See ``docs/plugins.md`` for the reference; a test fails if a hook here is missing from it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pluggy

hookspec = pluggy.HookspecMarker("calstation")

RegisterDriver = Callable[[str, str, Callable[..., Any]], None]
"""``register(kind, name, factory)``: kind is "lidar", "turntable" or "encoder"."""

RegisterStrategy = Callable[[Any], None]
"""``register(strategy)``: an object implementing
:class:`calstation.plugins.cost_strategies.Strategy`."""

RegisterSimulator = Callable[[Any], None]
"""``register(simulator)``: an object implementing
:class:`calstation.plugins.simulation.Simulator`."""


@hookspec
def calstation_register_drivers(register: RegisterDriver) -> None:
    """Register driver factories. Called once when plugins load.

    Call ``register(kind, name, factory)`` for each driver, where ``kind`` is ``"lidar"``,
    ``"turntable"`` or ``"encoder"``, ``name`` is what recipes write in ``driver:``, and
    ``factory(settings, context)`` returns the driver (see :mod:`calstation.drivers`). Registering a
    name twice for one kind is an error.
    """


@hookspec
def calstation_register_cost_strategies(register: RegisterStrategy) -> None:
    """Register fine-tuning strategies. Called once when plugins load.

    Call ``register(strategy)`` with an object implementing
    :class:`calstation.plugins.cost_strategies.Strategy`; its ``name`` is what recipes write in
    ``calibration.strategy`` and what ``calstation calibrate --strategy`` accepts. An optional
    ``options_model`` (a pydantic model class) validates ``calibration.options[name]``; it must
    be a pydantic model class, or registering fails.
    """


@hookspec
def calstation_register_simulators(register: RegisterSimulator) -> None:
    """Register simulated stations. Called once when plugins load.

    Call ``register(simulator)`` with an object implementing
    :class:`calstation.plugins.simulation.Simulator`; its ``name`` is how
    :func:`calstation.plugins.simulator` finds it (``"sim"`` for the kit, the bench and
    ``calstation plan``). Registering a name twice is an error. calstation imports no simulator
    package: this hook is how it reaches one.
    """


@hookspec
def calstation_register_commands(cli: Any) -> None:
    """Add commands to the ``calstation`` CLI. ``cli`` is the root ``typer.Typer`` app."""


@hookspec
def calstation_fixture_placed(context: Any, fixture: str, geometry: Any) -> None:
    """The operator confirmed that ``fixture`` is on the platter (or ``--yes`` placed it).

    ``context`` is the run's :class:`calstation.drivers.DriverContext` (the simulator finds its
    scene in ``context.shared``), ``fixture`` one of ``"static_target"``,
    ``"spin_target"``, ``"qa_cube"``, or ``"none"`` when the platter is cleared; ``geometry`` is the
    recipe's model of that fixture. The simulated station uses it to put the fixture into its scene.
    """


@hookspec
def calstation_run_started(run: Any) -> None:
    """A run started, or a crashed run was resumed.

    ``run`` is the run's summary mapping (``id``, ``station``, ``recipe_name``,
    ``recipe_sha256``, ``operator``, ``status``, ``data_dir``, ...), as in
    ``calstation show --json`` at that moment.
    """


@hookspec
def calstation_step_finished(run: Any, step: str, status: str, result: Any) -> None:
    """A step of a run finished (its result is already committed to the database).

    ``run`` is the run's summary mapping (as for :func:`calstation_run_started`), ``step`` the
    step name (``"preflight"``, ``"place_static_target"``, ``"static_scan"``, ...), ``status``
    ``"passed"`` or ``"failed"``, ``result`` the step's JSON-ready result mapping (for a failed
    step: ``{"error": message}``; a failed cube check is a failed ``cube_scan`` with its whole
    result, as its measurements are kept). Observers (a factory MES upload, say) implement this; an
    exception raised here is reported but does not fail the run.
    """


@hookspec
def calstation_run_finished(run: Any, status: str, summary: Any) -> None:
    """A run ended with ``status`` (``"passed"``, ``"failed"`` or ``"aborted"``).

    ``run`` is the run's summary mapping; ``summary`` the full record as printed by
    ``calstation show --json`` (steps, calibrations, cube check, artifacts).
    """
