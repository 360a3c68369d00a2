"""Registers the simulated station's drivers (``sim``), the simulator itself (``sim``: what
calstation's kit, bench and ``calstation plan`` simulate with) and the ``calstation simulate``
command."""

from __future__ import annotations

from collections.abc import Collection
from pathlib import Path
from typing import Any

from calstation import hookimpl
from calstation.plugins.hookspecs import RegisterDriver


@hookimpl
def calstation_register_drivers(register: RegisterDriver) -> None:
    """The ``sim`` lidar, turntable and encoder, sharing one station per run (the drivers,
    and Open3D with them, are imported when a run builds one)."""
    register("lidar", "sim", _lidar)
    register("turntable", "sim", _turntable)
    register("encoder", "sim", _encoder)


def _lidar(*args: Any, **kwargs: Any) -> Any:
    from .drivers import lidar_factory

    return lidar_factory(*args, **kwargs)


def _turntable(*args: Any, **kwargs: Any) -> Any:
    from .drivers import turntable_factory

    return turntable_factory(*args, **kwargs)


def _encoder(*args: Any, **kwargs: Any) -> Any:
    from .drivers import encoder_factory

    return encoder_factory(*args, **kwargs)


for _factory in (_lidar, _turntable, _encoder):
    # named by path: pydantic loads when a recipe is checked, not at registration
    _factory.settings_model = "calstation_sim.settings:SimSettings"  # type: ignore[attr-defined]


class Simulator:
    """The ray-cast station as a :class:`calstation.plugins.simulators.Simulator` (its modules,
    and Open3D with them, are imported when it simulates)."""

    name = "sim"

    def simulate_run(
        self, loaded: Any, out: Path, *, seed: int | None = None, range_m: float | None = None,
        pitch_deg: float | None = None, progress: bool = True,
        only: Collection[str] | None = None,
    ) -> dict[str, Path]:
        """:func:`calstation_sim.run.simulate_run`."""
        from .run import simulate_run

        return simulate_run(loaded, out, seed=seed, range_m=range_m, pitch_deg=pitch_deg,
                            progress=progress, only=only)

    def truth(
        self, loaded: Any, *, seed: int | None = None, range_m: float | None = None,
        pitch_deg: float | None = None,
    ) -> Any:
        """:attr:`calstation_sim.station.SimulatedStation.truth`."""
        from .station import SimulatedStation

        return SimulatedStation(loaded, seed=seed, range_m=range_m, pitch_deg=pitch_deg).truth


@hookimpl
def calstation_register_simulators(register: Any) -> None:
    """The ray-cast simulated station."""
    register(Simulator())


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
