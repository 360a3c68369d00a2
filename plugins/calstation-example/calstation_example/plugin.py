"""The example plugin's hook implementations: drivers, a strategy, a run observer, a command.

Drivers (``example`` lidar, turntable, encoder) are in :mod:`calstation_example.drivers`, the
strategy (``example-ry-held``) in :mod:`calstation_example.strategy`.

Set ``CALSTATION_EXAMPLE_LOG`` to a file path to switch the observer on; each event is appended
as one JSON line (UTF-8), flushed at once so a crash never loses an event already reported.
"""

from __future__ import annotations

import datetime as dt
import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from calstation import hookimpl
from calstation.jsonvalue import JSONObject, JSONValue
from calstation.plugins.hookspecs import RegisterDriver, RegisterStrategy, RunBrief, RunSummary

if TYPE_CHECKING:
    from calstation.drivers import DriverContext

    from .drivers import ExampleEncoder, ExampleLidar, ExampleTurntable

ENV = "CALSTATION_EXAMPLE_LOG"


@hookimpl
def calstation_register_drivers(register: RegisterDriver) -> None:
    """Register the ``example`` lidar, turntable and encoder."""
    register("lidar", "example", lidar_factory)
    register("turntable", "example", turntable_factory)
    register("encoder", "example", encoder_factory)


# the drivers (and NumPy with them) load when a run builds one, not at registration
def lidar_factory(settings: Mapping[str, object], context: DriverContext) -> ExampleLidar:
    """The ``example`` lidar (:func:`calstation_example.drivers.lidar_factory`)."""
    from .drivers import lidar_factory as make

    return make(settings, context)


def turntable_factory(
    settings: Mapping[str, object], context: DriverContext
) -> ExampleTurntable:
    """The ``example`` turntable (:func:`calstation_example.drivers.turntable_factory`)."""
    from .drivers import turntable_factory as make

    return make(settings, context)


def encoder_factory(settings: Mapping[str, object], context: DriverContext) -> ExampleEncoder:
    """The ``example`` encoder (:func:`calstation_example.drivers.encoder_factory`)."""
    from .drivers import encoder_factory as make

    return make(settings, context)


@hookimpl
def calstation_register_cost_strategies(register: RegisterStrategy) -> None:
    """Register the ``example-ry-held`` strategy (its options model, and pydantic with it,
    loads when the strategy registry is built, not at start-up)."""
    from .strategy import RyHeldStrategy

    register(RyHeldStrategy())


def log_path() -> Path | None:
    """The JSON-lines file named by ``CALSTATION_EXAMPLE_LOG`` (None: observer off)."""
    value = os.environ.get(ENV)
    return Path(value).expanduser() if value else None


def append_event(event: str, run: RunBrief, **fields: object) -> None:
    """Append ``{"event", "time", "run_id", "station", ...fields}`` to the log, if switched on."""
    path = log_path()
    if path is None:
        return
    record = {
        "event": event,
        "time": dt.datetime.now(dt.UTC).isoformat(),
        "run_id": run["id"],
        "station": run["station"],
        **fields,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("a", encoding="utf-8") as f:
        f.write(json.dumps(record, default=str) + "\n")
        f.flush()


def read_events(path: Path) -> list[JSONObject]:
    """Every event in a log written by :func:`append_event`."""
    events: list[JSONObject] = []
    with path.open(encoding="utf-8") as f:
        for line in f:
            if line.strip():
                event: JSONValue = json.loads(line)
                if not isinstance(event, dict):
                    raise ValueError(f"{path}: a line of the log is not an event: {line[:80]!r}")
                events.append(event)
    return events


@hookimpl
def calstation_run_started(run: RunBrief) -> None:
    """Log the start (or resumption) of a run."""
    append_event("run_started", run, recipe=run["recipe_name"], operator=run["operator"])


@hookimpl
def calstation_step_finished(run: RunBrief, step: str, status: str, result: JSONObject) -> None:
    """Log a finished step with its result."""
    append_event("step_finished", run, step=step, status=status, result=dict(result or {}))


@hookimpl
def calstation_run_finished(run: RunBrief, status: str, summary: RunSummary) -> None:
    """Log the end of a run with its final calibration, if any."""
    final = next((c for c in summary["calibrations"] if c.get("accepted")), None)
    append_event("run_finished", run, status=status, calibration=final)


@hookimpl
def calstation_register_commands(cli: typer.Typer) -> None:
    """Add ``calstation example-log``."""

    @cli.command("example-log")
    def example_log(
        file: Path = typer.Argument(None, help="Log file (default: $CALSTATION_EXAMPLE_LOG)."),
    ) -> None:
        """Print the example plugin's run log."""
        from rich.console import Console
        from rich.table import Table

        path = file or log_path()
        if path is None or not path.is_file():
            typer.echo(f"no run log (set {ENV} and run a recipe)")
            raise typer.Exit(1)
        table = Table(title=str(path))
        for col in ("time", "event", "run", "step", "status"):
            table.add_column(col)
        for e in read_events(path):
            table.add_row(
                str(e["time"]), str(e["event"]), str(e.get("run_id")), str(e.get("step", "")),
                str(e.get("status", "")),
            )
        Console().print(table)
