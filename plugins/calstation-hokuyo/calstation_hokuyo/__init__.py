"""Hokuyo SCIP 2.0 line scanners for calstation: the ``hokuyo`` lidar driver and its emulator.

The package's names load their modules (and NumPy and pyserial) when first used, so that
registering the plugin costs nothing at start-up.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the names as mypy sees them; at run time __getattr__ imports them when used
    from calstation.testing.transports import PtyServer, TcpServer

    from .driver import ClockSync, HokuyoLidar, SensorParameters, StepMapping
    from .emulator import ScipParameters, ScipSensor, WallScene
    from .scip import HokuyoError, ScipChecksumError, ScipStatusError, ScipTimeout

__all__ = [
    "ClockSync",
    "HokuyoError",
    "HokuyoLidar",
    "PtyServer",
    "ScipChecksumError",
    "ScipParameters",
    "ScipSensor",
    "ScipStatusError",
    "ScipTimeout",
    "SensorParameters",
    "StepMapping",
    "TcpServer",
    "WallScene",
]

_WHERE = {
    "ClockSync": ".driver",
    "HokuyoLidar": ".driver",
    "SensorParameters": ".driver",
    "StepMapping": ".driver",
    "ScipParameters": ".emulator",
    "ScipSensor": ".emulator",
    "WallScene": ".emulator",
    "HokuyoError": ".scip",
    "ScipChecksumError": ".scip",
    "ScipStatusError": ".scip",
    "ScipTimeout": ".scip",
    "PtyServer": "calstation.testing.transports",
    "TcpServer": "calstation.testing.transports",
}


def __getattr__(name: str) -> object:
    """Import the module that defines ``name`` when it is first used."""
    if name not in _WHERE:
        raise AttributeError(f"module 'calstation_hokuyo' has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(_WHERE[name], __name__), name)
