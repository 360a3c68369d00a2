"""The simulated calibration station: a ray-cast scene behind calstation's driver interfaces.

The package's names load their modules (and Open3D) when first used, and the plugin module
(:mod:`calstation_sim.plugin`) registers factories that import the drivers when a run builds
them, so ``calstation --help`` stays fast.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the names as mypy sees them; at run time __getattr__ imports them when used
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

_WHERE = {
    "SimEncoder": "drivers",
    "SimLidar": "drivers",
    "SimTurntable": "drivers",
    "SimulatedStation": "station",
    "shared_station": "station",
    "simulate_run": "run",
}


def __getattr__(name: str) -> object:
    """Import the heavy modules (Open3D) only when one of their names is used."""
    if name not in _WHERE:
        raise AttributeError(f"module 'calstation_sim' has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(f".{_WHERE[name]}", __name__), name)
