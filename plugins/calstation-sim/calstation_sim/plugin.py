"""Registers the simulated station's drivers (``sim``) and the ``calstation simulate`` command."""

from __future__ import annotations

from typing import Any

from calstation import hookimpl
from calstation.hookspecs import RegisterDriver


@hookimpl
def calstation_register_drivers(register: RegisterDriver) -> None:
    """The ``sim`` lidar, turntable and encoder, sharing one station per run."""
    from . import drivers

    register("lidar", "sim", drivers.lidar_factory)
    register("turntable", "sim", drivers.turntable_factory)
    register("encoder", "sim", drivers.encoder_factory)


@hookimpl
def calstation_fixture_placed(context: Any, fixture: str, geometry: Any) -> None:
    """Put ``fixture`` into the simulated scene, when this run is simulated."""
    shared = getattr(context, "shared", None)
    station = shared.get("sim") if isinstance(shared, dict) else None
    if station is not None:
        station.place(fixture)


@hookimpl
def calstation_register_commands(cli: Any) -> None:
    """``calstation simulate``."""
    from .cli import register

    register(cli)
