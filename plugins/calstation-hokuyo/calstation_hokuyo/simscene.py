"""The run's simulated station, as the scene behind in-process emulators (``emulate: true``)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from calstation.drivers import DriverContext

from .scip import HokuyoError

if TYPE_CHECKING:
    from calstation_sim import SimulatedStation


def simulated_station(context: DriverContext) -> SimulatedStation:
    """The run's shared ``calstation_sim.SimulatedStation`` (``calstation_sim.shared_station``),
    created on the host clock when no other driver made it yet, so the emulators run in real
    time."""
    try:
        from calstation_sim import shared_station
    except ImportError as exc:
        raise HokuyoError(
            "emulate: true needs the calstation-sim plugin (pip install -e plugins/calstation-sim)"
        ) from exc
    return shared_station(context, clock=context.clock)
