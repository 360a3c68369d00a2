"""Every hook calstation calls, in one place. Plugins implement them with ``@hookimpl``.

See ``docs/plugins.md`` for the reference; a test fails if a hook here is missing from it.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any, TypedDict

import pluggy

from calstation.jsonvalue import JSONObject

if TYPE_CHECKING:
    import typer

    from calstation.drivers import DriverContext, Encoder, Lidar, Turntable
    from calstation.plugins.cost_strategies import Strategy
    from calstation.plugins.simulation import Simulator

hookspec = pluggy.HookspecMarker("calstation")

LidarFactory = Callable[[Mapping[str, object], "DriverContext"], "Lidar"]
"""``factory(settings, context)`` of a lidar driver: the recipe's ``settings`` mapping."""

TurntableFactory = Callable[[Mapping[str, object], "DriverContext"], "Turntable"]
"""``factory(settings, context)`` of a turntable driver."""

EncoderFactory = Callable[[Mapping[str, object], "DriverContext"], "Encoder"]
"""``factory(settings, context)`` of an encoder driver."""

DriverFactory = LidarFactory | TurntableFactory | EncoderFactory
"""A driver factory of any kind."""

RegisterDriver = Callable[[str, str, DriverFactory], None]
"""``register(kind, name, factory)``: kind is "lidar", "turntable" or "encoder"."""

RegisterStrategy = Callable[["Strategy"], None]
"""``register(strategy)``: an object implementing
:class:`calstation.plugins.cost_strategies.Strategy`."""

RegisterSimulator = Callable[["Simulator"], None]
"""``register(simulator)``: an object implementing
:class:`calstation.plugins.simulation.Simulator`."""


# --- what the observer hooks receive -----------------------------------------------------------
class RunBrief(TypedDict):
    """The run as the observer hooks receive it (``run``): its own fields, as in
    ``calstation show --json`` (UTC ISO-8601 times)."""

    id: int
    station: str
    recipe_name: str
    recipe_path: str | None
    recipe_sha256: str
    operator: str
    unit_serial: str | None
    unattended: bool
    status: str
    started_at: str | None
    finished_at: str | None
    data_dir: str
    error: str | None
    host: str | None
    pid: int | None
    motor_stop: JSONObject | None


class StepRecord(TypedDict):
    """One attempt of a step in a :class:`RunSummary`."""

    name: str
    attempt: int
    status: str
    started_at: str | None
    finished_at: str | None
    result: JSONObject | None
    error: str | None


class ArtifactRecord(TypedDict):
    """One file of a run in a :class:`RunSummary` (``path`` in its run folder or store)."""

    kind: str
    step: str | None
    path: str
    size_bytes: int | None
    sha256: str | None
    status: str


class RunSummary(RunBrief):
    """The run's whole record (``summary`` of ``calstation_run_finished``): the brief and its
    steps, calibrations, cube check, QA limits and files, as ``calstation show --json`` prints
    it."""

    steps: list[StepRecord]
    calibrations: list[JSONObject]
    cube_check: JSONObject | None
    qa_limits: JSONObject | None
    artifacts: list[ArtifactRecord]


# Any: the storage layer's run mapping (``calstation.storage.report.run_summary``), read here
# key by key into the payload the hooks declare.
def run_brief_payload(record: Mapping[str, Any]) -> RunBrief:
    """The :class:`RunBrief` of a stored run's mapping (its other keys left out)."""
    return RunBrief(
        id=record["id"], station=record["station"], recipe_name=record["recipe_name"],
        recipe_path=record["recipe_path"], recipe_sha256=record["recipe_sha256"],
        operator=record["operator"], unit_serial=record["unit_serial"],
        unattended=record["unattended"], status=record["status"],
        started_at=record["started_at"], finished_at=record["finished_at"],
        data_dir=record["data_dir"], error=record["error"], host=record["host"],
        pid=record["pid"], motor_stop=record["motor_stop"],
    )


def run_summary_payload(record: Mapping[str, Any]) -> RunSummary:
    """The :class:`RunSummary` of a stored run's whole mapping."""
    return {**run_brief_payload(record), "steps": record["steps"],
            "calibrations": record["calibrations"], "cube_check": record["cube_check"],
            "qa_limits": record["qa_limits"], "artifacts": record["artifacts"]}


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
def calstation_register_commands(cli: typer.Typer) -> None:
    """Add commands to the ``calstation`` CLI. ``cli`` is the root ``typer.Typer`` app."""


@hookspec
def calstation_fixture_placed(context: DriverContext, fixture: str, geometry: object) -> None:
    """The operator confirmed that ``fixture`` is on the platter (or ``--yes`` placed it).

    ``context`` is the run's :class:`calstation.drivers.DriverContext` (the simulator finds its
    scene in ``context.shared``), ``fixture`` one of ``"static_target"``,
    ``"spin_target"``, ``"qa_cube"``, or ``"none"`` when the platter is cleared; ``geometry`` is the
    recipe's model of that fixture. The simulated station uses it to put the fixture into its scene.
    """


@hookspec
def calstation_run_started(run: RunBrief) -> None:
    """A run started, or a crashed run was resumed.

    ``run`` is the run's :class:`RunBrief` (``id``, ``station``, ``recipe_name``,
    ``recipe_sha256``, ``operator``, ``status``, ``data_dir``, ...), as in
    ``calstation show --json`` at that moment.
    """


@hookspec
def calstation_step_finished(run: RunBrief, step: str, status: str, result: JSONObject) -> None:
    """A step of a run finished (its result is already committed to the database).

    ``run`` is the run's summary mapping (as for :func:`calstation_run_started`), ``step`` the
    step name (``"preflight"``, ``"place_static_target"``, ``"static_scan"``, ...), ``status``
    ``"passed"`` or ``"failed"``, ``result`` the step's JSON-ready result mapping (for a failed
    step: ``{"error": message}``; a failed cube check is a failed ``cube_scan`` with its whole
    result, as its measurements are kept). Observers (a factory MES upload, say) implement this; an
    exception raised here is reported but does not fail the run.
    """


@hookspec
def calstation_run_finished(run: RunBrief, status: str, summary: RunSummary) -> None:
    """A run ended with ``status`` (``"passed"``, ``"failed"`` or ``"aborted"``).

    ``run`` is the run's :class:`RunBrief`; ``summary`` the full record (:class:`RunSummary`) as
    printed by ``calstation show --json`` (steps, calibrations, cube check, artifacts).
    """
