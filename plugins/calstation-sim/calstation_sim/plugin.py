"""Registers the simulated station's drivers (``sim``), the simulator itself (``sim``: what
calstation's kit, bench and ``calstation plan`` simulate with) and the ``calstation simulate``
command."""

from __future__ import annotations

from collections.abc import Collection, Mapping
from pathlib import Path
from typing import TYPE_CHECKING

from calstation import hookimpl
from calstation.plugins.hookspecs import RegisterDriver, RegisterSimulator

if TYPE_CHECKING:
    import typer

    from calstation.drivers import DriverContext
    from calstation.engine.frames import Extrinsics
    from calstation.recipes import LoadedRecipe

    from .drivers import SimEncoder, SimLidar, SimTurntable


@hookimpl
def calstation_register_drivers(register: RegisterDriver) -> None:
    """The ``sim`` lidar, turntable and encoder, sharing one station per run (the drivers,
    and Open3D with them, are imported when a run builds one)."""
    register("lidar", "sim", _lidar)
    register("turntable", "sim", _turntable)
    register("encoder", "sim", _encoder)


def _lidar(settings: Mapping[str, object], context: DriverContext) -> SimLidar:
    from .drivers import lidar_factory

    return lidar_factory(settings, context)


def _turntable(settings: Mapping[str, object], context: DriverContext) -> SimTurntable:
    from .drivers import turntable_factory

    return turntable_factory(settings, context)


def _encoder(settings: Mapping[str, object], context: DriverContext) -> SimEncoder:
    from .drivers import encoder_factory

    return encoder_factory(settings, context)


for _factory in (_lidar, _turntable, _encoder):
    # named by path: pydantic loads when a recipe is checked, not at registration
    _factory.settings_model = "calstation_sim.settings:SimSettings"  # type: ignore[union-attr]


class Simulator:
    """The ray-cast station as a :class:`calstation.plugins.simulators.Simulator` (its modules,
    and Open3D with them, are imported when it simulates)."""

    name = "sim"

    def simulate_run(
        self, loaded: LoadedRecipe, out: Path, *, seed: int | None = None,
        range_m: float | None = None, pitch_deg: float | None = None, progress: bool = True,
        only: Collection[str] | None = None,
    ) -> dict[str, Path]:
        """:func:`calstation_sim.run.simulate_run`."""
        from .run import simulate_run

        return simulate_run(loaded, out, seed=seed, range_m=range_m, pitch_deg=pitch_deg,
                            progress=progress, only=only)

    def truth(
        self, loaded: LoadedRecipe, *, seed: int | None = None, range_m: float | None = None,
        pitch_deg: float | None = None,
    ) -> Extrinsics:
        """:attr:`calstation_sim.station.SimulatedStation.truth`."""
        from .station import SimulatedStation

        return SimulatedStation(loaded, seed=seed, range_m=range_m, pitch_deg=pitch_deg).truth


@hookimpl
def calstation_register_simulators(register: RegisterSimulator) -> None:
    """The ray-cast simulated station."""
    register(Simulator())


@hookimpl
def calstation_fixture_placed(context: DriverContext, fixture: str, geometry: object) -> None:
    """Put ``fixture`` into the simulated scene, when this run is simulated."""
    shared = getattr(context, "shared", None)
    station = shared.get("sim") if isinstance(shared, dict) else None
    if station is not None:
        station.place(fixture)


@hookimpl
def calstation_register_commands(cli: typer.Typer) -> None:
    """``calstation simulate``."""
    from .cli import register

    register(cli)
