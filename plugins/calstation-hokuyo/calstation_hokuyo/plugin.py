"""Registers the ``hokuyo`` lidar driver and the ``calstation emulate hokuyo`` command.

The factory imports the driver (and NumPy and pyserial) when a run builds one
(:mod:`calstation_hokuyo.emulated`), so that registering it costs nothing at start-up.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from calstation import hookimpl
from calstation.cli import command_group

if TYPE_CHECKING:
    from calstation_sim import SimulatedStation

    from calstation.clock import Clock
    from calstation.drivers import DriverContext
    from calstation.plugins.hookspecs import RegisterDriver

    from .driver import HokuyoLidar


def make_lidar(settings: Mapping[str, object], context: DriverContext) -> HokuyoLidar:
    """Factory of the ``hokuyo`` lidar driver (settings: see docs/drivers.md)."""
    from .emulated import make_lidar as make

    return make(settings, context)


@hookimpl
def calstation_register_drivers(register: RegisterDriver) -> None:
    """Register lidar ``hokuyo``."""
    register("lidar", "hokuyo", make_lidar)


_EMULATE_HELP = "Run device emulators that speak the real wire protocols."


@hookimpl
def calstation_register_commands(cli: typer.Typer) -> None:
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
        from calstation.testing.transports import PtyServer, TcpServer

        from .emulator import ScipParameters, ScipSensor, WallScene
        from .scip import HokuyoError

        clock = HostClock()
        station: SimulatedStation | None = None
        if recipe is not None:
            from calstation_sim import SimulatedStation

            from calstation.recipes import load_recipe

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


def _console(station: SimulatedStation | None, clock: Clock) -> None:
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
