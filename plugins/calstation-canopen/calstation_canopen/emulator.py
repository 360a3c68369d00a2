"""CANopen device emulators on python-can: a CiA 402 drive and a CiA 406 encoder.

Both are :class:`calstation.testing.canbus.EmulatedNode` subclasses (calstation's CAN emulator
kit: a ``canopen.LocalNode`` with working PDOs, SYNC-latched sampling and a heartbeat consumer);
this module adds only the two device profiles.

The motion comes from a *platter*: ``set_speed(rpm, t_ns)``, ``platter_angle(t_ns)`` (rad) and
``platter_speed_rpm(t_ns)`` — the simulated station's real-time building blocks, or
:class:`RampPlatter` for tests without a scene. Turning the emulated motor turns that platter.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable
from typing import Protocol

import canopen

from calstation.clock import Clock, HostClock
from calstation.testing.canbus import (
    I8,
    I32,
    U16,
    U32,
    EmulatedNode,
    add_pdo_objects,
    add_variable,
)

from . import cia402 as ds

log = logging.getLogger(__name__)



class Platter(Protocol):
    """What a drive emulator turns (SimulatedStation's real-time building blocks)."""

    def set_speed(self, rpm: float, t_ns: int) -> object:
        """Command ``rpm`` (signed, + = right-handed about +X_P) at host time ``t_ns``."""
        ...

    def platter_angle(self, t_ns: int) -> float:
        """Platter angle φ (rad, unwrapped) at ``t_ns``."""
        ...

    def platter_speed_rpm(self, t_ns: int) -> float:
        """Platter speed (rpm) at ``t_ns``."""
        ...


class RampPlatter:
    """A platter with a constant-acceleration ramp, for tests without a simulated scene."""

    def __init__(self, acceleration_rpm_s: float = 120.0, clock: Clock | None = None) -> None:
        self.acceleration_rpm_s = acceleration_rpm_s
        self._t0 = (clock or HostClock()).now_ns()
        self._segments: list[tuple[float, float, float, float]] = [(0.0, 0.0, 0.0, 0.0)]
        self._lock = threading.Lock()

    def _state(self, t: float) -> tuple[float, float]:
        """(angle rad, speed rpm) at t seconds since start."""
        t_start, phi0, v0, v1 = next(s for s in reversed(self._segments) if s[0] <= t)
        ramp = abs(v1 - v0) / self.acceleration_rpm_s
        dt = t - t_start
        to_rad = 2 * math.pi / 60
        if dt < ramp:
            v = v0 + math.copysign(self.acceleration_rpm_s, v1 - v0) * dt
            return phi0 + (v0 + v) / 2 * dt * to_rad, v
        return phi0 + ((v0 + v1) / 2 * ramp + v1 * (dt - ramp)) * to_rad, v1

    def set_speed(self, rpm: float, t_ns: int) -> None:
        """Ramp to ``rpm`` from ``t_ns`` on."""
        t = (t_ns - self._t0) / 1e9
        with self._lock:
            phi, v = self._state(t)
            self._segments.append((t, phi, v, float(rpm)))

    def platter_angle(self, t_ns: int) -> float:
        """φ (rad) at ``t_ns``."""
        with self._lock:
            return self._state((t_ns - self._t0) / 1e9)[0]

    def platter_speed_rpm(self, t_ns: int) -> float:
        """Speed (rpm) at ``t_ns``."""
        with self._lock:
            return self._state((t_ns - self._t0) / 1e9)[1]


class DriveEmulator(EmulatedNode):
    """A CiA 402 drive in profile velocity mode turning ``platter``.

    Units: target/actual velocity in ``velocity_unit_rpm`` rpm per unit (default 0.01 rpm),
    position actual in ``counts_per_revolution`` per platter turn (default 10000), ``direction``
    +1 when positive velocity turns the platter right-handed about +X_P.
    Default mapping: RPDO1 = controlword + target velocity; TPDO1 = statusword + position actual;
    TPDO2 = velocity actual; both TPDOs on every SYNC.
    """

    device_type = 0x0002_0192  # CiA 402, servo drive

    def __init__(self, platter: Platter, *, node_id: int = 1, interface: str = "virtual",
                 channel: str = "calstation", clock: Clock | None = None,
                 velocity_unit_rpm: float = 0.01, counts_per_revolution: int = 10_000,
                 direction: int = 1, heartbeat_ms: int = 0) -> None:
        self.platter = platter
        self.velocity_unit_rpm = velocity_unit_rpm
        self.counts_per_revolution = counts_per_revolution
        self.direction = direction
        self.state = ds.DriveState.SWITCH_ON_DISABLED
        self._last_cw = 0
        self.commanded_rpm = 0.0
        self.faults: list[int] = []
        super().__init__(node_id, interface, channel, clock, heartbeat_ms)

    def build_od(self, od: canopen.ObjectDictionary) -> None:
        """CiA 402 objects and the default PDO mappings."""
        add_variable(od, "error code", ds.ERROR_CODE, U16, 0, "ro")
        add_variable(od, "controlword", ds.CONTROLWORD, U16, 0)
        add_variable(od, "statusword", ds.STATUSWORD, U16, 0x0240, "ro")
        add_variable(od, "modes of operation", ds.MODES_OF_OPERATION, I8, 0)
        add_variable(od, "modes of operation display", ds.MODES_OF_OPERATION_DISPLAY, I8, 0, "ro")
        add_variable(od, "position actual value", ds.POSITION_ACTUAL, I32, 0, "ro")
        add_variable(od, "velocity actual value", ds.VELOCITY_ACTUAL, I32, 0, "ro")
        add_variable(od, "target velocity", ds.TARGET_VELOCITY, I32, 0)
        add_variable(od, "profile acceleration", ds.PROFILE_ACCELERATION, U32, 0)
        add_variable(od, "quick stop deceleration", ds.QUICK_STOP_DECELERATION, U32, 0)
        add_variable(od, "supported drive modes", ds.SUPPORTED_DRIVE_MODES, U32,
                     ds.SUPPORTS_PROFILE_VELOCITY | 0x0001, "ro")
        add_pdo_objects(od, self.node_id, rpdos=[[0x60400010, 0x60FF0020]],
                        tpdos=[[0x60410010, 0x60640020], [0x606C0020]])

    # --- state machine ---------------------------------------------------------------------
    def statusword(self) -> int:
        """The statusword of the current state (remote, voltage and target-reached bits)."""
        sw = self.state.bits | ds.SW_REMOTE
        if self.state in (ds.DriveState.READY_TO_SWITCH_ON, ds.DriveState.SWITCHED_ON,
                          ds.DriveState.OPERATION_ENABLED, ds.DriveState.QUICK_STOP_ACTIVE):
            sw |= ds.SW_VOLTAGE_ENABLED
        if self.state is ds.DriveState.OPERATION_ENABLED:
            now = self.clock.now_ns()
            if abs(self.platter.platter_speed_rpm(now) - self.commanded_rpm) < 0.01:
                sw |= ds.SW_TARGET_REACHED
        return sw

    def _controlword(self, cw: int) -> None:
        S = ds.DriveState
        rising_reset = bool(cw & 0x80) and not self._last_cw & 0x80
        self._last_cw = cw
        st = self.state
        if st in (S.FAULT, S.FAULT_REACTION_ACTIVE):
            if rising_reset:
                self.faults.clear()
                self.store(ds.ERROR_CODE, 0, 0)
                self.emcy(0x0000)
                self.state = S.SWITCH_ON_DISABLED
            return
        if not cw & 0x02:  # disable voltage
            self.state = S.SWITCH_ON_DISABLED
        elif not cw & 0x04:  # quick stop
            self.state = S.QUICK_STOP_ACTIVE if st is S.OPERATION_ENABLED else (
                S.QUICK_STOP_ACTIVE if st is S.QUICK_STOP_ACTIVE else S.SWITCH_ON_DISABLED)
        elif cw & 0x0F == 0x06:  # shutdown
            if st in (S.SWITCH_ON_DISABLED, S.SWITCHED_ON, S.OPERATION_ENABLED,
                      S.READY_TO_SWITCH_ON):
                self.state = S.READY_TO_SWITCH_ON
        elif cw & 0x0F == 0x07:  # switch on / disable operation
            if st in (S.READY_TO_SWITCH_ON, S.OPERATION_ENABLED, S.SWITCHED_ON):
                self.state = S.SWITCHED_ON
        elif cw & 0x0F == 0x0F and st in (S.SWITCHED_ON, S.OPERATION_ENABLED,
                                           S.QUICK_STOP_ACTIVE):  # enable operation
            self.state = S.OPERATION_ENABLED
        self._apply_motion()

    def _apply_motion(self) -> None:
        rpm = 0.0
        if (self.state is ds.DriveState.OPERATION_ENABLED
                and self.value(ds.MODES_OF_OPERATION) == ds.MODE_PROFILE_VELOCITY):
            rpm = self.direction * self.value(ds.TARGET_VELOCITY) * self.velocity_unit_rpm
        if rpm != self.commanded_rpm:
            self.commanded_rpm = rpm
            self.platter.set_speed(rpm, self.clock.now_ns())

    def on_write(self, index: int, subindex: int, value: int) -> None:
        """Controlword drives the state machine; target velocity and mode change the motion."""
        if index == ds.CONTROLWORD:
            self._controlword(value)
        elif index in (ds.TARGET_VELOCITY, ds.MODES_OF_OPERATION):
            if index == ds.MODES_OF_OPERATION:
                self.store(ds.MODES_OF_OPERATION_DISPLAY, 0, value)
            self._apply_motion()

    def on_read(self, index: int, subindex: int) -> int | None:
        """Statusword, position and velocity are live, latched at the SYNC being answered."""
        now = self.sample_time_ns()
        if index == ds.STATUSWORD:
            return self.statusword()
        if index == ds.POSITION_ACTUAL:
            counts = round(self.direction * self.platter.platter_angle(now) / (2 * math.pi)
                           * self.counts_per_revolution)
            return (counts + 2**31) % 2**32 - 2**31  # an i32 register wraps
        if index == ds.VELOCITY_ACTUAL:
            return round(self.direction * self.platter.platter_speed_rpm(now)
                         / self.velocity_unit_rpm)
        return None

    def inject_fault(self, code: int = 0x2310) -> None:
        """Go to FAULT with EMCY ``code`` (the motor coasts to a stop)."""
        with self._lock:
            self.faults.append(code)
            self.store(ds.ERROR_CODE, 0, code)
            self.state = ds.DriveState.FAULT
            self._apply_motion()
            self.emcy(code)

    def on_master_lost(self) -> None:
        """Heartbeat consumer timeout: fault 0x8130, stop the motor."""
        log.warning("drive emulator: master heartbeat lost; stopping")
        if self.state is not ds.DriveState.FAULT:
            self.faults.append(0x8130)
            self.store(ds.ERROR_CODE, 0, 0x8130)
            self.state = ds.DriveState.FAULT
            self._apply_motion()
            self.emcy(0x8130)


class EncoderEmulator(EmulatedNode):
    """A CiA 406 rotary encoder reading ``count(t_ns)`` (an unwrapped count).

    0x6001 measuring units per revolution = ``counts_per_revolution``; 0x6002 total measuring
    range (the position value 0x6004 wraps there); 0x6003 preset; 0x6200 cyclic timer (ms).
    TPDO1 maps 0x6004 (4 bytes) and defaults to transmission type 1 (every SYNC).
    """

    device_type = 0x0001_0196  # CiA 406, single-turn rotary encoder

    def __init__(self, count: Callable[[int], int], counts_per_revolution: int, *,
                 node_id: int = 2, interface: str = "virtual", channel: str = "calstation",
                 clock: Clock | None = None, total_range: int = 1 << 32,
                 heartbeat_ms: int = 0) -> None:
        self.count = count
        self.counts_per_revolution = counts_per_revolution
        self.total_range = total_range
        super().__init__(node_id, interface, channel, clock, heartbeat_ms)

    def build_od(self, od: canopen.ObjectDictionary) -> None:
        """CiA 406 objects and TPDO1 = position value."""
        add_variable(od, "operating parameters", 0x6000, U16, 0)
        add_variable(od, "measuring units per revolution", 0x6001, U32,
                     self.counts_per_revolution)
        add_variable(od, "total measuring range", 0x6002, U32, self.total_range % (1 << 32))
        add_variable(od, "preset value", 0x6003, U32, 0)
        add_variable(od, "position value", 0x6004, U32, 0, "ro")
        add_variable(od, "cyclic timer", 0x6200, U16, 0)
        add_pdo_objects(od, self.node_id, rpdos=[], tpdos=[[0x60040020]])

    def position_value(self, t_ns: int) -> int:
        """0x6004 at ``t_ns``: direction bit of 0x6000 applied, preset added, wrapped."""
        c = self.count(t_ns)
        if self.value(0x6000) & 0x0001:  # code sequence: counter-clockwise counting
            c = -c
        return (c + self.value(0x6003)) % self.total_range

    def on_read(self, index: int, subindex: int) -> int | None:
        """The position value is live."""
        if index == 0x6004:
            return self.position_value(self.sample_time_ns())
        return None

    def cyclic_period_ms(self, k: int) -> int:
        """Type 0xFE/0xFF with 0x6200 > 0 (or an event timer): cyclic."""
        if self.value(0x1800 + k, 2) < 0xFE:
            return 0
        return self.value(0x6200) or self.value(0x1800 + k, 5)
