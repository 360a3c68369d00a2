"""The simulated calibration station: a ray-cast scene behind calstation's driver interfaces.

Importing this package pulls in Open3D; the plugin module (:mod:`calstation_sim.plugin`) imports
it lazily so ``calstation --help`` stays fast.
"""

from __future__ import annotations

from .drivers import SimEncoder, SimLidar, SimTurntable
from .run import simulate_run
from .station import SimulatedStation, shared_station

__all__ = [
    "SimEncoder",
    "SimLidar",
    "SimTurntable",
    "SimulatedStation",
    "shared_station",
    "simulate_run",
]
