"""Registers the ``hokuyo`` lidar driver and the ``calstation emulate hokuyo`` command."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import typer

from calstation import hookimpl
from calstation.cli import command_group
from calstation.drivers import DriverContext
from calstation.testing.transports import PtyServer, TcpServer

from .driver import HokuyoLidar
from .emulator import ScipParameters, ScipSensor, WallScene
from .scip import HokuyoError


class EmulatedHokuyo(HokuyoLidar):
    """The ``hokuyo`` driver talking, through real SCIP bytes on a local TCP port, to an emulator
    backed by the run's simulated station (``settings.emulate: true``). Closing the driver stops
    the emulator."""

    def __init__(self, settings: Mapping[str, Any], context: DriverContext) -> None:
        from .simscene import simulated_station

        station = simulated_station(context)
        # the emulated sensor is mounted the way the driver's settings say (azimuth_sign)
        params = ScipParameters(azimuth_sign=int(settings.get("azimuth_sign", -1)))
        self.emulator = ScipSensor(station.scan_line, params, now_ns=context.clock.now_ns)
        self.server = TcpServer(self.emulator)
        cfg = {k: v for k, v in settings.items() if k not in ("emulate", "port")}
        super().__init__({**cfg, "port": self.server.url}, clock=context.clock)

    def close(self) -> None:
        """Close the driver, then the emulator."""
        super().close()
        self.server.close()


def make_lidar(settings: Mapping[str, Any], context: DriverContext) -> HokuyoLidar:
    """Factory of the ``hokuyo`` lidar driver (settings: see docs/drivers.md)."""
    if settings.get("emulate"):
        return EmulatedHokuyo(settings, context)
    return HokuyoLidar(settings, clock=context.clock)


@hookimpl
def calstation_register_drivers(register: Any) -> None:
    """Register lidar ``hokuyo``."""
    register("lidar", "hokuyo", make_lidar)


_EMULATE_HELP = "Run device emulators that speak the real wire protocols."


@hookimpl
def calstation_register_commands(cli: Any) -> None:
    """Add ``calstation emulate hokuyo``."""
    emulate = command_group(cli, "emulate", _EMULATE_HELP)

    @emulate.command("hokuyo")
    def emulate_hokuyo(
        port: int = typer.Option(10940, "--port", help="TCP port to listen on (0: any free)."),
        host: str = typer.Option("127.0.0.1", "--host", help="Address to listen on."),
        pty: bool = typer.Option(False, "--pty", help="Serve on a pseudo-terminal instead."),
        recipe: Path | None = typer.Option(
            None, "--recipe", help="Back the scan with this recipe's simulated station."
        ),
        fixture: str = typer.Option(
            "static_target", "--fixture",
            help="Fixture on the simulated platter: static_target, spin_target, qa_cube, none.",
        ),
        rpm: float = typer.Option(0.0, "--rpm", help="Spin the simulated platter at this speed."),
        seed: int | None = typer.Option(None, "--seed", help="Simulation seed."),
    ) -> None:
        """Serve an emulated SCIP 2.0 lidar until interrupted (Ctrl-C).

        Type 'place FIXTURE' or 'spin RPM' on stdin to change the scene while it runs.
        """
        from calstation.clock import HostClock

        clock = HostClock()
        station: Any = None
        if recipe is not None:
            from calstation_sim import SimulatedStation

            from calstation.recipe import load_recipe

            station = SimulatedStation(load_recipe(recipe), seed=seed, clock=clock)
            station.place(fixture)
            if rpm:
                station.set_speed(rpm, clock.now_ns())
            sensor = ScipSensor(station.scan_line, ScipParameters(), now_ns=clock.now_ns)
        else:
            sensor = ScipSensor(WallScene(), ScipParameters(), now_ns=clock.now_ns)
        server: TcpServer | PtyServer
        try:
            server = PtyServer(sensor) if pty else TcpServer(sensor, host=host, port=port)
        except OSError as exc:
            raise HokuyoError(f"emulate hokuyo: cannot listen on {host}:{port}: {exc}") from exc
        p = sensor.params
        typer.echo(f"SCIP 2.0 emulator on {server.url}  (ARES {p.ares}, AMIN {p.amin}, "
                   f"AMAX {p.amax}, AFRT {p.afrt}, SCAN {p.scan_rpm} rpm)", err=False)
        typer.echo("Ctrl-C to stop" + ("; 'place FIXTURE' / 'spin RPM' on stdin" if station
                                       else ""))
        try:
            _console(station, clock)
        finally:
            server.close()


def _console(station: Any, clock: Any) -> None:
    """Read 'place FIXTURE' / 'spin RPM' commands from stdin; idle when stdin is closed."""
    while True:
        try:
            line = input()
        except EOFError:
            while True:
                time.sleep(3600)
        words = line.split()
        if station is None or len(words) != 2:
            continue
        with contextlib.suppress(Exception):
            if words[0] == "place":
                station.place(words[1])
                typer.echo(f"placed {words[1]}")
            elif words[0] == "spin":
                station.set_speed(float(words[1]), clock.now_ns())
                typer.echo(f"platter at {float(words[1]):g} rpm")
