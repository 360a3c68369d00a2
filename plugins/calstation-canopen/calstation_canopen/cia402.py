"""CiA 402 drive profile: object indices, controlword commands and statusword states."""

from __future__ import annotations

import enum

CONTROLWORD = 0x6040
STATUSWORD = 0x6041
MODES_OF_OPERATION = 0x6060
MODES_OF_OPERATION_DISPLAY = 0x6061
POSITION_ACTUAL = 0x6064
VELOCITY_ACTUAL = 0x606C
TARGET_VELOCITY = 0x60FF
PROFILE_ACCELERATION = 0x6083
QUICK_STOP_DECELERATION = 0x6085
SUPPORTED_DRIVE_MODES = 0x6502
ERROR_CODE = 0x603F
CONSUMER_HEARTBEAT = 0x1016
PRODUCER_HEARTBEAT = 0x1017

MODE_PROFILE_VELOCITY = 3
SUPPORTS_PROFILE_VELOCITY = 0x0004

CW_SHUTDOWN = 0x06
CW_SWITCH_ON = 0x07
CW_ENABLE_OPERATION = 0x0F
CW_QUICK_STOP = 0x02
CW_DISABLE_VOLTAGE = 0x00
CW_FAULT_RESET = 0x80

SW_REMOTE = 0x0200
SW_TARGET_REACHED = 0x0400
SW_VOLTAGE_ENABLED = 0x0010


class DriveState(enum.Enum):
    """CiA 402 power state machine states, with their statusword (mask, value)."""

    NOT_READY_TO_SWITCH_ON = (0x4F, 0x00)
    SWITCH_ON_DISABLED = (0x4F, 0x40)
    READY_TO_SWITCH_ON = (0x6F, 0x21)
    SWITCHED_ON = (0x6F, 0x23)
    OPERATION_ENABLED = (0x6F, 0x27)
    QUICK_STOP_ACTIVE = (0x6F, 0x07)
    FAULT_REACTION_ACTIVE = (0x4F, 0x0F)
    FAULT = (0x4F, 0x08)

    @property
    def bits(self) -> int:
        """The statusword bits of this state (under its mask)."""
        return self.value[1]


def state_of(statusword: int) -> DriveState:
    """The drive state a statusword reports (the most specific match first)."""
    for state in (
        DriveState.OPERATION_ENABLED,
        DriveState.SWITCHED_ON,
        DriveState.READY_TO_SWITCH_ON,
        DriveState.QUICK_STOP_ACTIVE,
        DriveState.FAULT_REACTION_ACTIVE,
        DriveState.FAULT,
        DriveState.SWITCH_ON_DISABLED,
        DriveState.NOT_READY_TO_SWITCH_ON,
    ):
        mask, value = state.value
        if statusword & mask == value:
            return state
    return DriveState.NOT_READY_TO_SWITCH_ON


EMCY_MEANINGS: dict[int, str] = {
    0x0000: "error reset / no error",
    0x1000: "generic error",
    0x2310: "continuous over-current",
    0x3210: "DC link over-voltage",
    0x4210: "excess temperature",
    0x5441: "safe torque off",
    0x7121: "motor blocked",
    0x8130: "heartbeat or life guard error",
    0x8611: "following error",
    0xFF00: "manufacturer specific",
}


def emcy_text(code: int) -> str:
    """``0xCODE (meaning)`` for an EMCY error code."""
    meaning = EMCY_MEANINGS.get(code) or EMCY_MEANINGS.get(code & 0xFF00, "device specific")
    return f"EMCY 0x{code:04X} ({meaning})"
