"""The ``canopen402`` and ``canopen406`` factories, and their in-process emulators on the
simulated station (``emulate: true``); registered by :mod:`calstation_canopen.plugin`."""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from calstation.drivers import DriverContext
from calstation.testing.canbus import EmulatedNode

from .bus import CanopenError
from .drive import Cia402Turntable
from .emulator import DriveEmulator, EncoderEmulator
from .encoder import Cia406Encoder

if TYPE_CHECKING:
    from calstation_sim import SimulatedStation


def _simulated_station(context: DriverContext) -> SimulatedStation:
    """The run's shared simulated station (``calstation_sim.shared_station``), created on the
    host clock when no other driver made it yet, so the emulators run in real time."""
    try:
        from calstation_sim import shared_station
    except ImportError as exc:
        raise CanopenError(
            "emulate: true needs the calstation-sim plugin (pip install -e plugins/calstation-sim)"
        ) from exc
    return shared_station(context, clock=context.clock)


def _emulators(context: DriverContext) -> dict[str, EmulatedNode]:
    found: dict[str, EmulatedNode] = context.shared.setdefault("canopen_emulators", {})
    return found


def _close_emulator(context: DriverContext | None, kind: str) -> None:
    """Stop the run's emulated ``kind`` ("drive" or "encoder"), if one is running."""
    if context is not None:
        emu = _emulators(context).pop(kind, None)
        if emu is not None:
            emu.close()


def _with_emulator(
    settings: Mapping[str, object], context: DriverContext, kind: str
) -> dict[str, object]:
    """Start the emulated device for a driver with ``emulate: true`` (virtual bus by default)."""
    cfg: dict[str, Any] = dict(settings)  # Any: the recipe's settings, as the emulators read them
    if not cfg.pop("emulate", False):
        return cfg
    cfg.setdefault("interface", "virtual")
    cfg.setdefault("channel", "calstation-emulated")
    station = _simulated_station(context)
    emulators = _emulators(context)
    if kind not in emulators:
        common = {"interface": cfg["interface"], "channel": str(cfg["channel"]),
                  "clock": context.clock}
        if kind == "drive":
            emulators[kind] = DriveEmulator(
                station, node_id=int(cfg.get("node_id", 1)), heartbeat_ms=0,
                velocity_unit_rpm=float(cfg.get("velocity_unit_rpm", 0.01)),
                counts_per_revolution=int(cfg.get("counts_per_revolution", 10_000)),
                direction=int(cfg.get("direction", 1)), **common)
        else:
            emulators[kind] = EncoderEmulator(
                station.encoder_count, station.counts_per_revolution,
                node_id=int(cfg.get("node_id", 2)), **common)
    return cfg


class EmulatedTurntable(Cia402Turntable):
    """``canopen402`` against an in-process emulated drive turning the simulated platter."""

    def close(self) -> None:
        """Close the driver, then its emulator."""
        super().close()
        _close_emulator(self.context, "drive")


class EmulatedEncoder(Cia406Encoder):
    """``canopen406`` against an in-process emulated encoder on the simulated platter."""

    def close(self) -> None:
        """Close the driver, then its emulator."""
        super().close()
        _close_emulator(self.context, "encoder")


def make_turntable(settings: Mapping[str, object], context: DriverContext) -> Cia402Turntable:
    """Factory of ``canopen402`` (``emulate: true`` adds an in-process emulated drive)."""
    if settings.get("emulate"):
        return EmulatedTurntable(_with_emulator(settings, context, "drive"), context)
    return Cia402Turntable(settings, context)


def make_encoder(settings: Mapping[str, object], context: DriverContext) -> Cia406Encoder:
    """Factory of ``canopen406`` (``emulate: true`` adds an in-process emulated encoder)."""
    if settings.get("emulate"):
        return EmulatedEncoder(_with_emulator(settings, context, "encoder"), context)
    return Cia406Encoder(settings, context)
