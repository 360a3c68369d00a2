"""CANopen drivers for calstation: a CiA 402 turntable drive and a CiA 406 encoder, with
emulators of both on python-can.

The package's names load their modules (and python-can) when first used, so that registering
the plugin costs nothing at start-up.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the names as mypy sees them; at run time __getattr__ imports them when used
    from calstation.testing.canbus import EmulatedNode

    from .bus import CanopenError, SharedBus
    from .drive import Cia402Turntable
    from .emulator import DriveEmulator, EncoderEmulator, RampPlatter
    from .encoder import Cia406Encoder, Unwrapper

__all__ = [
    "CanopenError",
    "Cia402Turntable",
    "Cia406Encoder",
    "DriveEmulator",
    "EmulatedNode",
    "EncoderEmulator",
    "RampPlatter",
    "SharedBus",
    "Unwrapper",
]

_WHERE = {
    "CanopenError": "bus",
    "SharedBus": "bus",
    "Cia402Turntable": "drive",
    "DriveEmulator": "emulator",
    "EmulatedNode": "emulator",
    "EncoderEmulator": "emulator",
    "RampPlatter": "emulator",
    "Cia406Encoder": "encoder",
    "Unwrapper": "encoder",
}


def __getattr__(name: str) -> object:
    """Import the module that defines ``name`` when it is first used."""
    if name not in _WHERE:
        raise AttributeError(f"module 'calstation_canopen' has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(f".{_WHERE[name]}", __name__), name)
