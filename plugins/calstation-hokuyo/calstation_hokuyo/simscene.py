"""The run's simulated station, as the scene behind in-process emulators (``emulate: true``)."""

from __future__ import annotations

from typing import Any

from calstation.drivers import DriverContext

from .scip import HokuyoError


def simulated_station(context: DriverContext) -> Any:
    """The run's ``calstation_sim.SimulatedStation`` (``context.shared["sim"]``), created on the
    host clock when no other driver made it yet, so the emulators run in real time."""
    try:
        from calstation_sim import SimulatedStation
    except ImportError as exc:
        raise HokuyoError(
            "emulate: true needs the calstation-sim plugin (pip install -e plugins/calstation-sim)"
        ) from exc
    if context.recipe is None:
        raise HokuyoError("emulate: true needs the run's recipe (its simulation section)")
    station = context.shared.get("sim")
    if station is None:
        station = SimulatedStation(context.recipe, clock=context.clock)
        context.shared["sim"] = station
    return station
