"""Hokuyo SCIP 2.0 line scanners for calstation: the ``hokuyo`` lidar driver and its emulator."""

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
