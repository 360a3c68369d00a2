"""Registers turntable ``canopen402``, encoder ``canopen406`` and ``calstation emulate canopen``.

The factories import the drivers (and python-can) when a run builds one
(:mod:`calstation_canopen.emulated`), so that registering them costs nothing at start-up.
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
    from calstation.drivers import DriverContext
    from calstation.plugins.hookspecs import RegisterDriver
    from calstation.testing.transports import TcpServer

    from .drive import Cia402Turntable
    from .emulator import DriveEmulator, EncoderEmulator
    from .encoder import Cia406Encoder


def make_turntable(settings: Mapping[str, object], context: DriverContext) -> Cia402Turntable:
    """Factory of ``canopen402`` (``emulate: true`` adds an in-process emulated drive)."""
    from .emulated import make_turntable as make

    return make(settings, context)


def make_encoder(settings: Mapping[str, object], context: DriverContext) -> Cia406Encoder:
    """Factory of ``canopen406`` (``emulate: true`` adds an in-process emulated encoder)."""
    from .emulated import make_encoder as make

    return make(settings, context)


# the settings' models import pydantic: named by path, loaded when a recipe is checked
make_turntable.settings_model = "calstation_canopen.settings:Cia402Settings"  # type: ignore[attr-defined]
make_encoder.settings_model = "calstation_canopen.settings:Cia406Settings"  # type: ignore[attr-defined]


@hookimpl
def calstation_register_drivers(register: RegisterDriver) -> None:
    """Turntable ``canopen402`` and encoder ``canopen406``."""
    register("turntable", "canopen402", make_turntable)
    register("encoder", "canopen406", make_encoder)


_EMULATE_HELP = "Run device emulators that speak the real wire protocols."


@hookimpl
def calstation_register_commands(cli: typer.Typer) -> None:
    """Add ``calstation emulate canopen``."""
    emulate = command_group(cli, "emulate", _EMULATE_HELP)

    @emulate.command("canopen")
    def emulate_canopen(
        recipe: Path = typer.Option(..., "--recipe", help="Recipe whose simulated station to run."),
        interface: str = typer.Option(
            "udp_multicast", "--interface",
            help="python-can interface (udp_multicast across processes)."),
        channel: str = typer.Option("239.74.163.2", "--channel", help="CAN channel / group."),
        drive_node: int = typer.Option(1, "--drive-node", help="Node id of the CiA 402 drive."),
        encoder_node: int = typer.Option(2, "--encoder-node", help="Node id of the encoder."),
        hokuyo_port: int | None = typer.Option(
            None, "--hokuyo-port", help="Also serve the SCIP 2.0 lidar on this TCP port."),
        fixture: str = typer.Option("static_target", "--fixture", help="Fixture on the platter."),
        seed: int | None = typer.Option(None, "--seed", help="Simulation seed."),
    ) -> None:
        """Emulate the CiA 402 drive and CiA 406 encoder (and optionally the lidar) of one
        simulated station until interrupted. Type 'place FIXTURE' on stdin to change fixtures."""
        from calstation_sim import SimulatedStation

        from calstation.clock import HostClock
        from calstation.recipes import load_recipe

        from .emulator import DriveEmulator, EncoderEmulator

        clock = HostClock()
        station = SimulatedStation(load_recipe(recipe), seed=seed, clock=clock)
        station.place(fixture)
        nodes: list[DriveEmulator | EncoderEmulator | TcpServer] = [
            DriveEmulator(station, node_id=drive_node, interface=interface, channel=channel,
                          clock=clock),
            EncoderEmulator(station.encoder_count, station.counts_per_revolution,
                            node_id=encoder_node, interface=interface, channel=channel,
                            clock=clock),
        ]
        typer.echo(f"CiA 402 drive node {drive_node}, CiA 406 encoder node {encoder_node} on "
                   f"{interface}:{channel}")
        if hokuyo_port is not None:
            from calstation_hokuyo import ScipParameters, ScipSensor, TcpServer

            sensor = ScipSensor(station.scan_line, ScipParameters(azimuth_sign=1),
                                now_ns=clock.now_ns)
            server = TcpServer(sensor, port=hokuyo_port)
            nodes.append(server)
            typer.echo(f"SCIP 2.0 lidar on {server.url} (mounted with azimuth_sign 1)")
        try:
            while True:
                try:
                    words = input().split()
                except EOFError:
                    while True:
                        time.sleep(3600)
                if len(words) == 2 and words[0] == "place":
                    with contextlib.suppress(Exception):
                        station.place(words[1])
                        typer.echo(f"placed {words[1]}")
        finally:
            for node in nodes:
                node.close()
