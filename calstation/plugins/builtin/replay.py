"""Registers the ``replay`` lidar, turntable and encoder (:mod:`calstation.recordings.replay`).

The factories import the drivers (and NumPy and the recording reader with them) when a run
builds one, so that registering them costs nothing at start-up.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING

from calstation import hookimpl
from calstation.plugins.hookspecs import RegisterDriver

if TYPE_CHECKING:
    from calstation.drivers import DriverContext
    from calstation.recordings.replay import ReplayEncoder, ReplayLidar, ReplayTurntable

DRIVER_NAME = "replay"


def replay_lidar(settings: Mapping[str, object], context: DriverContext) -> ReplayLidar:
    """Factory of the ``replay`` lidar."""
    from calstation.recordings.replay import replay_lidar as make

    return make(settings, context)


def replay_turntable(settings: Mapping[str, object], context: DriverContext) -> ReplayTurntable:
    """Factory of the ``replay`` turntable."""
    from calstation.recordings.replay import replay_turntable as make

    return make(settings, context)


def replay_encoder(settings: Mapping[str, object], context: DriverContext) -> ReplayEncoder:
    """Factory of the ``replay`` encoder."""
    from calstation.recordings.replay import replay_encoder as make

    return make(settings, context)


@hookimpl
def calstation_register_drivers(register: RegisterDriver) -> None:
    """Register the ``replay`` lidar, turntable and encoder."""
    register("lidar", DRIVER_NAME, replay_lidar)
    register("turntable", DRIVER_NAME, replay_turntable)
    register("encoder", DRIVER_NAME, replay_encoder)


@hookimpl
def calstation_fixture_placed(context: DriverContext, fixture: str, geometry: object) -> None:
    """A folder replay switches to the recording of the fixture now on the platter."""
    shared = getattr(context, "shared", None)
    if not isinstance(shared, dict):
        return
    for session in shared.get("replay", {}).values():
        session.place(fixture)
