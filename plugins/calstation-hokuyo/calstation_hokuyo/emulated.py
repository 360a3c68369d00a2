"""The ``hokuyo`` factory and its emulated variant (``emulate: true``); registered by
:mod:`calstation_hokuyo.plugin`."""

from __future__ import annotations

from collections.abc import Mapping

from calstation.drivers import DriverContext
from calstation.testing.transports import TcpServer

from .driver import HokuyoLidar
from .emulator import ScipParameters, ScipSensor
from .scip import HokuyoError


class EmulatedHokuyo(HokuyoLidar):
    """The ``hokuyo`` driver talking, through real SCIP bytes on a local TCP port, to an emulator
    backed by the run's simulated station (``settings.emulate: true``). Closing the driver stops
    the emulator."""

    def __init__(self, settings: Mapping[str, object], context: DriverContext) -> None:
        from .simscene import simulated_station

        station = simulated_station(context)
        # the emulated sensor is mounted the way the driver's settings say (azimuth_sign)
        sign = settings.get("azimuth_sign", -1)
        if not isinstance(sign, int | float | str):
            raise HokuyoError(f"hokuyo driver: settings.azimuth_sign must be 1 or -1, not {sign!r}")
        params = ScipParameters(azimuth_sign=int(sign))
        self.emulator = ScipSensor(station.scan_line, params, now_ns=context.clock.now_ns)
        self.server = TcpServer(self.emulator)
        cfg = {k: v for k, v in settings.items() if k not in ("emulate", "port")}
        super().__init__({**cfg, "port": self.server.url}, clock=context.clock)

    def close(self) -> None:
        """Close the driver, then the emulator."""
        super().close()
        self.server.close()


def make_lidar(settings: Mapping[str, object], context: DriverContext) -> HokuyoLidar:
    """Factory of the ``hokuyo`` lidar driver (settings: see docs/drivers.md)."""
    if settings.get("emulate"):
        return EmulatedHokuyo(settings, context)
    return HokuyoLidar(settings, clock=context.clock)
