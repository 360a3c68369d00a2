"""The ``canopen402`` turntable driver: a CiA 402 drive in profile velocity mode.

Start-up (``enable``): NMT pre-operational; SDO: modes of operation 0x6060 = 3 (profile velocity,
checked against 0x6502), producer heartbeat 0x1017, consumer heartbeat 0x1016 (the drive stops
if this master goes silent); PDO mapping — RPDO1 = controlword 0x6040 + target velocity 0x60FF,
TPDO1 = statusword 0x6041 + position actual 0x6064, TPDO2 = velocity actual 0x606C, both on every
SYNC; NMT start; fault reset if needed; then the enable sequence 0x06 → 0x07 → 0x0F, each step
confirmed by the statusword. Every later command goes by RPDO1 only (never an SDO write of the
controlword or target velocity: the next RPDO would overwrite it). A status is stamped with the
host time of the SYNC its TPDO1 answers (the drive latches its position there), as the
``canopen406`` encoder stamps its samples.

EMCY frames are recorded as faults; when the drive's heartbeat stops for ``heartbeat_timeout_s``
the driver reports a fault, sends a quick stop and refuses to spin until re-enabled.
"""

from __future__ import annotations

import contextlib
import logging
import math
import struct
import threading
import time
from collections.abc import Mapping
from typing import Any

from canopen.network import Callback

from calstation.drivers import DriverContext, TurntableState, TurntableStatus

from . import cia402 as ds
from .bus import BusNodeDriver, CanopenError, CanopenTimeout, release_bus

log = logging.getLogger(__name__)

SETTINGS_DEFAULTS: dict[str, object] = {
    "interface": "socketcan",
    "channel": None,
    "bitrate": 500_000,
    "node_id": 1,
    "master_id": 127,
    "velocity_unit_rpm": 0.01,
    "counts_per_revolution": 10_000,
    "direction": 1,
    "sync_period_s": 0.01,
    "heartbeat_period_s": 0.1,
    "heartbeat_timeout_s": 0.5,
    "master_heartbeat_s": 0.1,
    "sdo_timeout_s": 0.5,
    "state_timeout_s": 1.0,
    "stop_timeout_s": 15.0,
    "stop_tolerance_rpm": 0.05,
    "move_rpm": 2.0,
    "move_tolerance_rad": 0.002,
    "emulate": False,
}
"""Recipe ``settings`` of the ``canopen402`` driver and their defaults (docs/drivers.md)."""


def check_settings(name: str, settings: Mapping[str, object], defaults: Mapping[str, object]
                   ) -> dict[str, Any]:  # Any: the recipe's settings, converted where read
    """Settings merged over defaults; unknown keys are a :class:`CanopenError` naming them."""
    unknown = sorted(set(settings) - set(defaults))
    if unknown:
        raise CanopenError(
            f"{name} driver: unknown setting(s) {', '.join(unknown)}; known: "
            f"{', '.join(sorted(defaults))}"
        )
    return {**defaults, **settings}


class Cia402Turntable(BusNodeDriver):
    """A CiA 402 drive behind calstation's :class:`~calstation.drivers.Turntable` protocol."""

    driver_name = "canopen402"

    def __init__(
        self, settings: Mapping[str, object], context: DriverContext | None = None
    ) -> None:
        self.settings = check_settings("canopen402", settings, SETTINGS_DEFAULTS)
        self._attach_node(self.settings, context)
        self._lock = threading.RLock()
        self._statusword: int | None = None
        self._position: int | None = None
        self._velocity: int | None = None
        self._pdo_time_ns = 0
        self._last_sync_ns = 0
        self._position_unwrapped: int | None = None
        self._heartbeat_ns: int | None = None
        self.heartbeat_lost = False
        self.faults: list[str] = []
        self._controlword = 0
        self._target = 0
        self._enabled = False
        self._closed = False
        self._stop = threading.Event()
        self._subscriptions: list[tuple[int, Callback]] = []
        self._monitor: threading.Thread | None = None

    # --- low level -------------------------------------------------------------------------
    def _subscribe(self, cob: int, cb: Callback) -> None:
        self.network.subscribe(cob, cb)
        self._subscriptions.append((cob, cb))

    def send_rpdo(self, controlword: int, target: int) -> None:
        """RPDO1: controlword (u16) + target velocity (i32), little-endian."""
        with self._lock:
            self._controlword, self._target = controlword, target
            self.network.send_message(0x200 + self.node_id,
                                      struct.pack("<Hi", controlword, target))

    def _configure_pdo(self, comm: int, mapping: int, cob: int, entries: list[int],
                       kind: int) -> None:
        self.sdo_write(comm, 1, "<I", 0x8000_0000 | cob)  # disable while remapping
        self.sdo_write(mapping, 0, "<B", 0)
        for i, entry in enumerate(entries, start=1):
            self.sdo_write(mapping, i, "<I", entry)
        self.sdo_write(mapping, 0, "<B", len(entries))
        self.sdo_write(comm, 2, "<B", kind)
        self.sdo_write(comm, 1, "<I", cob)

    # --- callbacks -------------------------------------------------------------------------
    def _on_tpdo1(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if len(data) < 6:
            return
        sw, pos = struct.unpack_from("<Hi", data)
        # the drive latched its position at the SYNC this TPDO answers: stamped with that SYNC's
        # send time, not this callback's (a busy host runs it milliseconds later)
        now = self.clock.now_ns()
        t_sync = self.bus.pair_sync(self._last_sync_ns, now, self.bus.wire_ns(timestamp, now))
        with self._lock:
            self._statusword = sw
            if self._position is not None and self._position_unwrapped is not None:
                d = (pos - self._position + 2**31) % 2**32 - 2**31
                self._position_unwrapped += d
            else:
                self._position_unwrapped = pos
            self._position = pos
            if t_sync is not None:
                self._last_sync_ns = t_sync
            self._pdo_time_ns = now if t_sync is None else t_sync

    def _on_tpdo2(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if len(data) >= 4:
            with self._lock:
                self._velocity = struct.unpack_from("<i", data)[0]

    def _on_emcy(self, can_id: int, data: bytearray, timestamp: float) -> None:
        code = struct.unpack_from("<H", bytes(data).ljust(2, b"\0"))[0]
        text = ds.emcy_text(code)
        with self._lock:
            if code == 0:
                self.faults = [f for f in self.faults if not f.startswith("EMCY")]
            else:
                self.faults.append(text)
        log.warning("canopen402 node %d: %s", self.node_id, text)

    def _on_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        with self._lock:
            self._heartbeat_ns = self.clock.now_ns()

    def _watch_heartbeat(self) -> None:
        limit_ns = float(self.settings["heartbeat_timeout_s"]) * 1e9
        while not self._stop.wait(0.02):
            with self._lock:
                seen = self._heartbeat_ns
                lost = (self._enabled and seen is not None and not self.heartbeat_lost
                        and self.clock.now_ns() - seen > limit_ns)
                if lost:
                    self.heartbeat_lost = True
                    self.faults.append("heartbeat lost")
            if lost:
                log.error("canopen402 node %d: heartbeat lost; quick stop", self.node_id)
                self.emergency_stop()

    # --- protocol --------------------------------------------------------------------------
    def _statusword_now(self) -> int:
        sw = self.sdo_read(ds.STATUSWORD, 0, "<H")
        with self._lock:
            self._statusword = sw
        return sw

    def _wait_state(self, want: ds.DriveState, what: str) -> None:
        deadline = time.monotonic() + float(self.settings["state_timeout_s"])
        while True:
            sw = self._statusword_now()
            state = ds.state_of(sw)
            if state is want:
                return
            if state in (ds.DriveState.FAULT, ds.DriveState.FAULT_REACTION_ACTIVE):
                raise CanopenError(
                    f"canopen402 node {self.node_id}: drive in FAULT during {what} "
                    f"(statusword 0x{sw:04X}; {', '.join(self.faults) or 'no EMCY seen'})"
                )
            if time.monotonic() > deadline:
                raise CanopenTimeout(
                    f"canopen402 node {self.node_id}: {what}: drive stayed in {state.name} "
                    f"(statusword 0x{sw:04X}), expected {want.name}"
                )
            time.sleep(0.005)

    def enable(self) -> None:
        """NMT, SDO configuration, PDO mapping, then 0x06 → 0x07 → 0x0F."""
        s = self.settings
        if not self._subscriptions:
            self._subscribe(0x180 + self.node_id, self._on_tpdo1)
            self._subscribe(0x280 + self.node_id, self._on_tpdo2)
            self._subscribe(0x80 + self.node_id, self._on_emcy)
            self._subscribe(0x700 + self.node_id, self._on_heartbeat)
        self.node.nmt.state = "PRE-OPERATIONAL"
        try:
            modes = self.sdo_read(ds.SUPPORTED_DRIVE_MODES, 0, "<I")
        except CanopenError:
            modes = ds.SUPPORTS_PROFILE_VELOCITY  # 0x6502 is optional
        if not modes & ds.SUPPORTS_PROFILE_VELOCITY:
            raise CanopenError(
                f"canopen402 node {self.node_id}: the drive does not support profile velocity "
                f"mode (0x6502 = 0x{modes:08X})"
            )
        self.sdo_write(ds.MODES_OF_OPERATION, 0, "<b", ds.MODE_PROFILE_VELOCITY)
        hb_ms = round(float(s["heartbeat_period_s"]) * 1000)
        self.sdo_write(ds.PRODUCER_HEARTBEAT, 0, "<H", hb_ms)
        master_ms = round(float(s["master_heartbeat_s"]) * 1000)
        if master_ms:
            self.bus.start_heartbeat(int(s["master_id"]), master_ms / 1000)
            self.sdo_write(ds.CONSUMER_HEARTBEAT, 1, "<I",
                           (int(s["master_id"]) << 16) | (3 * master_ms))
        n = self.node_id
        self._configure_pdo(0x1400, 0x1600, 0x200 + n, [0x60400010, 0x60FF0020], 0xFF)
        self._configure_pdo(0x1800, 0x1A00, 0x180 + n, [0x60410010, 0x60640020], 0x01)
        self._configure_pdo(0x1801, 0x1A01, 0x280 + n, [0x606C0020], 0x01)
        self.bus.start_sync(float(s["sync_period_s"]))
        # SYNCs sent before the drive is operational are never answered
        self._last_sync_ns = self.clock.now_ns()
        self.node.nmt.state = "OPERATIONAL"
        with self._lock:
            self.heartbeat_lost = False
            self.faults = [f for f in self.faults if f != "heartbeat lost"]
            self._heartbeat_ns = self.clock.now_ns() if hb_ms else None
        if ds.state_of(self._statusword_now()) in (ds.DriveState.FAULT,
                                                   ds.DriveState.FAULT_REACTION_ACTIVE):
            self.fault_reset()
        for cw, state, what in (
            (ds.CW_SHUTDOWN, ds.DriveState.READY_TO_SWITCH_ON, "shutdown (0x06)"),
            (ds.CW_SWITCH_ON, ds.DriveState.SWITCHED_ON, "switch on (0x07)"),
            (ds.CW_ENABLE_OPERATION, ds.DriveState.OPERATION_ENABLED, "enable operation (0x0F)"),
        ):
            self.send_rpdo(cw, 0)
            self._wait_state(state, what)
        self._enabled = True
        if self._monitor is None:
            self._stop.clear()
            self._monitor = threading.Thread(target=self._watch_heartbeat,
                                             name="canopen402-heartbeat", daemon=True)
            self._monitor.start()

    def fault_reset(self) -> None:
        """Controlword 0x80 (rising edge), then back to switch-on-disabled."""
        self.send_rpdo(0x00, 0)
        self.send_rpdo(ds.CW_FAULT_RESET, 0)
        self._wait_state(ds.DriveState.SWITCH_ON_DISABLED, "fault reset (0x80)")
        with self._lock:
            self.faults = [f for f in self.faults if not f.startswith("EMCY")]

    def info(self) -> dict[str, str | int]:
        """Identity read by SDO: node id, device type 0x1000, supported drive modes 0x6502."""
        return {
            "protocol": "CANopen CiA 402",
            "bus": f"{self.bus.interface}:{self.bus.channel}",
            "node_id": self.node_id,
            "device_type": f"0x{self.sdo_read(0x1000, 0, '<I'):08X}",
            "supported_drive_modes": f"0x{self.sdo_read(ds.SUPPORTED_DRIVE_MODES, 0, '<I'):08X}",
        }

    def _units(self, rpm: float) -> int:
        return round(int(self.settings["direction"]) * rpm / float(self.settings[
            "velocity_unit_rpm"]))

    def _check_ready(self, what: str) -> None:
        if self.heartbeat_lost:
            raise CanopenError(
                f"canopen402 node {self.node_id}: cannot {what}: the drive's heartbeat was lost "
                "(check the bus and power, then enable again)"
            )
        if not self._enabled:
            raise CanopenError(f"canopen402 node {self.node_id}: cannot {what}: not enabled")
        sw = self._statusword
        if sw is not None and ds.state_of(sw) in (ds.DriveState.FAULT,
                                                  ds.DriveState.FAULT_REACTION_ACTIVE):
            raise CanopenError(
                f"canopen402 node {self.node_id}: cannot {what}: drive in FAULT "
                f"({', '.join(self.faults) or f'statusword 0x{sw:04X}'})"
            )

    def spin(self, rpm: float) -> None:
        """Target velocity ``rpm`` (signed, + = right-handed about +X_P), returns at once."""
        self._check_ready("spin")
        self.send_rpdo(ds.CW_ENABLE_OPERATION, self._units(rpm))

    def speed_rpm(self) -> float | None:
        """Velocity actual from TPDO2 (rpm), None before the first TPDO."""
        with self._lock:
            v = self._velocity
        if v is None:
            return None
        return v * float(self.settings["velocity_unit_rpm"]) * int(self.settings["direction"])

    def position_rad(self) -> float | None:
        """Position actual from TPDO1 (rad, unwrapped across the i32 wrap)."""
        with self._lock:
            p = self._position_unwrapped
        if p is None:
            return None
        return (int(self.settings["direction"]) * 2 * math.pi * p
                / int(self.settings["counts_per_revolution"]))

    def stop(self) -> None:
        """Target velocity 0; returns when velocity actual is within tolerance."""
        self._check_ready("stop")
        self.send_rpdo(ds.CW_ENABLE_OPERATION, 0)
        deadline = time.monotonic() + float(self.settings["stop_timeout_s"])
        tol = float(self.settings["stop_tolerance_rpm"])
        while True:
            v = self.speed_rpm()
            if v is not None and abs(v) <= tol:
                return
            if time.monotonic() > deadline:
                raise CanopenTimeout(
                    f"canopen402 node {self.node_id}: still turning at {v} rpm after "
                    f"{self.settings['stop_timeout_s']} s"
                )
            self._check_ready("stop")
            time.sleep(0.01)

    def move_to(self, angle_rad: float) -> None:
        """Turn at ``move_rpm`` the short way to ``angle_rad`` (mod 2π) and stop there."""
        self._check_ready("move")
        pos = self.position_rad()
        if pos is None:
            raise CanopenError(f"canopen402 node {self.node_id}: no position from TPDO1 yet")
        delta = (angle_rad - pos + math.pi) % (2 * math.pi) - math.pi
        target = pos + delta
        rpm = float(self.settings["move_rpm"])
        tol = float(self.settings["move_tolerance_rad"])
        if abs(delta) <= tol:
            return
        self.spin(math.copysign(rpm, delta))
        deadline = time.monotonic() + abs(delta) / (rpm * 2 * math.pi / 60) + 10
        while True:
            pos = self.position_rad()
            assert pos is not None
            if (target - pos) * math.copysign(1, delta) <= tol:
                break
            if time.monotonic() > deadline:
                self.emergency_stop()
                raise CanopenTimeout(f"canopen402 node {self.node_id}: move_to timed out")
            self._check_ready("move")
            time.sleep(0.002)
        self.stop()

    def emergency_stop(self) -> None:
        """Quick stop (controlword 0x02) by RPDO. Never raises."""
        with contextlib.suppress(Exception):
            self.send_rpdo(ds.CW_QUICK_STOP, 0)

    def disable(self) -> None:
        """Stop, then shutdown (0x06): motor power off, drive ready to switch on."""
        if self._enabled and not self.heartbeat_lost:
            try:
                self.stop()
            except CanopenError:
                self.emergency_stop()
        with contextlib.suppress(Exception):
            self.send_rpdo(ds.CW_SHUTDOWN, 0)
        self._enabled = False

    def status(self) -> TurntableStatus:
        """State, speed, position and faults from the latest TPDOs."""
        with self._lock:  # the time and the position of one TPDO
            sw = self._statusword
            t = self._pdo_time_ns or self.clock.now_ns()
            position = self.position_rad()
            faults = tuple(self.faults)
            lost = self.heartbeat_lost
        if sw is None:
            try:
                sw = self._statusword_now()
            except CanopenError as exc:
                return TurntableStatus(self.clock.now_ns(), TurntableState.FAULT, 0.0, None,
                                       (*faults, str(exc)))
        speed = self.speed_rpm() or 0.0
        state = ds.state_of(sw)
        if lost or state in (ds.DriveState.FAULT, ds.DriveState.FAULT_REACTION_ACTIVE):
            ts = TurntableState.FAULT
        elif state is ds.DriveState.QUICK_STOP_ACTIVE:
            ts = TurntableState.EMERGENCY_STOP
        elif state is ds.DriveState.OPERATION_ENABLED:
            moving = abs(speed) > float(self.settings["stop_tolerance_rpm"]) or self._target != 0
            ts = TurntableState.MOVING if moving else TurntableState.ENABLED
        else:
            ts = TurntableState.DISABLED
        if position is None:  # no TPDO yet (not enabled): ask by SDO
            with contextlib.suppress(CanopenError):
                counts = self.sdo_read(ds.POSITION_ACTUAL, 0, "<i")
                position = (int(self.settings["direction"]) * 2 * math.pi * counts
                            / int(self.settings["counts_per_revolution"]))
        return TurntableStatus(t, ts, speed, position, faults)

    def close(self) -> None:
        """Stop the motor (quick stop if a normal stop fails), disable, release the bus."""
        if self._closed:
            return
        self._closed = True
        with contextlib.suppress(Exception):
            self.disable()
        self._stop.set()
        if self._monitor is not None:
            self._monitor.join(timeout=1)
            self._monitor = None
        with contextlib.suppress(Exception):
            self.node.nmt.state = "PRE-OPERATIONAL"
        for cob, cb in self._subscriptions:
            with contextlib.suppress(Exception):
                self.network.unsubscribe(cob, cb)
        self._subscriptions.clear()
        release_bus(self.bus, self.context)

    def __enter__(self) -> Cia402Turntable:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
