"""CANopen drivers for calstation: a CiA 402 turntable drive and a CiA 406 encoder, with
emulators of both on python-can."""

from .bus import CanopenError, SharedBus
from .drive import Cia402Turntable
from .emulator import DriveEmulator, EmulatedNode, EncoderEmulator, RampPlatter
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
