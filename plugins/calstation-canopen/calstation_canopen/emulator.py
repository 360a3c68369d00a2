"""CANopen device emulators on python-can: a CiA 402 drive and a CiA 406 encoder.

Each emulator is a ``canopen.LocalNode`` (its SDO server and NMT slave come from the ``canopen``
package) on a network of its own, connected to the same CAN channel as the drivers (python-can's
``virtual`` interface in one process, ``udp_multicast`` across processes). :class:`EmulatedNode`
adds what LocalNode leaves out (PROTOCOLS.md's pitfalls):

- received RPDOs are decoded with the node's own mapping (0x1600+k) and written into the object
  dictionary through ``set_data``, so the write callbacks (the drive state machine) see them;
- TPDOs are built from the mapping (0x1A00+k) on SYNC (transmission type 1..240) or cyclically
  (0xFE with an event timer / the encoder's 0x6200), reading live values through read callbacks;
- the heartbeat consumer (0x1016) faults the drive when the master goes silent.

The motion comes from a *platter*: ``set_speed(rpm, t_ns)``, ``platter_angle(t_ns)`` (rad) and
``platter_speed_rpm(t_ns)`` — the simulated station's real-time building blocks, or
:class:`RampPlatter` for tests without a scene. Turning the emulated motor turns that platter.
"""

from __future__ import annotations

import contextlib
import logging
import math
import struct
import threading
import time
from collections.abc import Callable
from typing import Any, Protocol

import canopen
from canopen.objectdictionary import ODArray, ODRecord, ODVariable, datatypes

from calstation.clock import Clock, HostClock

from . import cia402 as ds
from .bus import SYNC_COB_ID

log = logging.getLogger(__name__)

U8, U16, U32 = datatypes.UNSIGNED8, datatypes.UNSIGNED16, datatypes.UNSIGNED32
I8, I16, I32 = datatypes.INTEGER8, datatypes.INTEGER16, datatypes.INTEGER32
_FORMATS = {U8: "<B", U16: "<H", U32: "<I", I8: "<b", I16: "<h", I32: "<i"}


class Platter(Protocol):
    """What a drive emulator turns (SimulatedStation's real-time building blocks)."""

    def set_speed(self, rpm: float, t_ns: int) -> Any:
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


# --- object dictionary helpers -------------------------------------------------------------------
def _var(name: str, index: int, sub: int, dtype: int, default: int, access: str = "rw"
         ) -> ODVariable:
    v = ODVariable(name, index, sub)
    v.data_type = dtype
    v.default = default
    v.access_type = access
    v.pdo_mappable = True
    return v


def add_variable(od: canopen.ObjectDictionary, name: str, index: int, dtype: int,
                 default: int = 0, access: str = "rw") -> None:
    """Add a plain variable ``index:00`` to ``od``."""
    od.add_object(_var(name, index, 0, dtype, default, access))


def add_record(od: canopen.ObjectDictionary, name: str, index: int,
               members: list[tuple[str, int, int]], array: bool = False) -> None:
    """Add a record (or array) whose sub0 is the number of entries; ``members`` are
    (name, dtype, default) for sub1, sub2, …"""
    rec: ODRecord | ODArray = ODArray(name, index) if array else ODRecord(name, index)
    rec.add_member(_var(f"{name} entries", index, 0, U8, len(members)))
    for i, (mname, dtype, default) in enumerate(members, start=1):
        rec.add_member(_var(mname, index, i, dtype, default))
    od.add_object(rec)


def add_pdo_objects(od: canopen.ObjectDictionary, node_id: int, rpdos: list[list[int]],
                    tpdos: list[list[int]], tpdo_type: int = 0x01) -> None:
    """Communication and mapping records for RPDOs (0x1400/0x1600+k) and TPDOs (0x1800/0x1A00+k)
    with default mappings (``0xIIIISSLL`` entries), 8 mapping slots each."""
    for k, mapping in enumerate(rpdos):
        add_record(od, f"RPDO{k + 1} communication", 0x1400 + k,
                   [("COB-ID", U32, 0x200 + 0x100 * k + node_id), ("type", U8, 0xFF)])
        add_record(od, f"RPDO{k + 1} mapping", 0x1600 + k,
                   [(f"entry {i + 1}", U32, mapping[i] if i < len(mapping) else 0)
                    for i in range(8)])
        od[0x1600 + k][0].default = len(mapping)
    for k, mapping in enumerate(tpdos):
        add_record(od, f"TPDO{k + 1} communication", 0x1800 + k,
                   [("COB-ID", U32, 0x180 + 0x100 * k + node_id), ("type", U8, tpdo_type),
                    ("inhibit time", U16, 0), ("reserved", U8, 0), ("event timer", U16, 0)])
        add_record(od, f"TPDO{k + 1} mapping", 0x1A00 + k,
                   [(f"entry {i + 1}", U32, mapping[i] if i < len(mapping) else 0)
                    for i in range(8)])
        od[0x1A00 + k][0].default = len(mapping)


class EmulatedNode:
    """A ``canopen.LocalNode`` on its own network, with working PDOs and heartbeat consumer.

    Subclasses build the object dictionary (:meth:`build_od`), react to writes
    (:meth:`on_write`) and supply live values (:meth:`on_read`).
    """

    def __init__(self, node_id: int, interface: str, channel: str,
                 clock: Clock | None = None, heartbeat_ms: int = 0) -> None:
        self.node_id = node_id
        self.clock: Clock = clock or HostClock()
        od = canopen.ObjectDictionary()
        add_variable(od, "device type", 0x1000, U32, self.device_type, "ro")
        add_variable(od, "error register", 0x1001, U8, 0, "ro")
        add_variable(od, "producer heartbeat time", ds.PRODUCER_HEARTBEAT, U16, heartbeat_ms)
        add_record(od, "consumer heartbeat time", ds.CONSUMER_HEARTBEAT, [("consumer 1", U32, 0)],
                   array=True)
        self.build_od(od)
        self.network = canopen.Network()
        self.network.connect(interface=interface, channel=channel)
        self.node = canopen.LocalNode(node_id, od)
        self.node.add_write_callback(self._write_cb)
        self.node.add_read_callback(self._read_cb)
        self.network.add_node(self.node)
        self.network.subscribe(SYNC_COB_ID, self._on_sync)
        self._rpdo_ids: dict[int, int] = {}
        self._sync_count = 0
        self._consumer_lock = threading.Lock()
        self._master_seen_ns: int | None = None
        self._master_id: int | None = None
        self._consumer_ms = 0
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._lock = threading.RLock()
        self.sent_tpdos = 0
        self._sample_ns = threading.local()
        self._subscribe_rpdos()
        self._spawn(self._monitor, "canopen-emulator-monitor")
        # boot-up: power on into PRE-OPERATIONAL, announce it, start the heartbeat producer
        self.network.send_message(0x700 + node_id, bytes([0x00]))
        self.node.nmt.send_command(0x80)
        if heartbeat_ms:
            self.node.nmt.start_heartbeat(heartbeat_ms)

    device_type = 0

    # --- subclass hooks --------------------------------------------------------------------
    def build_od(self, od: canopen.ObjectDictionary) -> None:
        """Add the device profile's objects."""

    def on_write(self, index: int, subindex: int, value: int) -> None:
        """A value was written (by SDO or RPDO)."""

    def on_read(self, index: int, subindex: int) -> int | None:
        """A live value, or None to use the stored one (sample it at :meth:`sample_time_ns`)."""
        return None

    def sample_time_ns(self) -> int:
        """When a live value is sampled: the bus time of the SYNC being answered, else now.

        A real device latches its inputs when the SYNC arrives; the emulator's thread may answer
        milliseconds later on a busy host, so it samples at the SYNC frame's own timestamp.
        """
        t = getattr(self._sample_ns, "t", None)
        return self.clock.now_ns() if t is None else int(t)

    def on_master_lost(self) -> None:
        """The master's heartbeat stopped (0x1016 consumer time exceeded)."""

    def poll(self) -> None:
        """Called every millisecond by the monitor thread (cyclic TPDOs, ramps)."""

    # --- plumbing ---------------------------------------------------------------------------
    def _spawn(self, target: Callable[[], None], name: str) -> None:
        t = threading.Thread(target=target, name=name, daemon=True)
        self._threads.append(t)
        t.start()

    def value(self, index: int, subindex: int = 0) -> int:
        """The stored (or live) value of an object, decoded."""
        obj = self.node._find_object(index, subindex)
        data = self.node.get_data(index, subindex)
        return int(struct.unpack(_FORMATS[obj.data_type], data)[0])

    def store(self, index: int, subindex: int, value: int) -> None:
        """Write a value into the object dictionary without running the write callbacks."""
        obj = self.node._find_object(index, subindex)
        self.node.data_store.setdefault(index, {})[subindex] = struct.pack(
            _FORMATS[obj.data_type], value)

    def _write_cb(self, index: int, subindex: int, od: ODVariable, data: bytes) -> None:
        value = int(struct.unpack(_FORMATS[od.data_type], data)[0])
        if index == ds.CONSUMER_HEARTBEAT and subindex == 1:
            with self._consumer_lock:
                self._master_id = (value >> 16) & 0x7F or None
                self._consumer_ms = value & 0xFFFF
                self._master_seen_ns = self.clock.now_ns()
                if self._master_id:
                    self.network.subscribe(0x700 + self._master_id, self._on_master_heartbeat)
        # store first so that on_write sees the new value through value()
        self.node.data_store.setdefault(index, {})[subindex] = bytes(data)
        if 0x1400 <= index <= 0x15FF and subindex == 1:
            self._subscribe_rpdos()
        with self._lock:
            self.on_write(index, subindex, value)

    def _read_cb(self, index: int, subindex: int, od: ODVariable) -> int | None:
        with self._lock:
            return self.on_read(index, subindex)

    def _subscribe_rpdos(self) -> None:
        for k in range(4):
            if 0x1400 + k not in self.node.object_dictionary:
                continue
            cob = self.value(0x1400 + k, 1)
            old = self._rpdo_ids.pop(k, None)
            if old is not None:
                with contextlib.suppress(Exception):
                    self.network.unsubscribe(old, self._rpdo_callbacks[k])
            if not cob & 0x8000_0000:
                self._rpdo_ids[k] = cob & 0x7FF
                self.network.subscribe(cob & 0x7FF, self._rpdo_callbacks[k])

    @property
    def _rpdo_callbacks(self) -> list[Callable[[int, bytearray, float], None]]:
        if not hasattr(self, "_rpdo_cb_list"):
            self._rpdo_cb_list = [
                (lambda cid, data, ts, k=k: self._on_rpdo(k, bytes(data))) for k in range(4)
            ]
        return self._rpdo_cb_list

    @property
    def operational(self) -> bool:
        """NMT state is OPERATIONAL (PDOs flow only then)."""
        return self.node.nmt.state == "OPERATIONAL"

    def mapping(self, index: int) -> list[tuple[int, int, int]]:
        """(index, subindex, bits) entries of a PDO mapping record."""
        n = self.value(index, 0)
        out = []
        for i in range(1, n + 1):
            e = self.value(index, i)
            out.append((e >> 16, (e >> 8) & 0xFF, e & 0xFF))
        return out

    def _on_rpdo(self, k: int, data: bytes) -> None:
        if not self.operational:
            return
        pos = 0
        # LocalNode does not copy RPDO data into its dictionary: do it, through set_data, so the
        # write callbacks (the state machine) run exactly as for an SDO write
        for index, sub, bits in self.mapping(0x1600 + k):
            n = bits // 8
            if pos + n > len(data):
                log.warning("RPDO%d too short for its mapping: %s", k + 1, data.hex())
                return
            self.node.set_data(index, sub, data[pos : pos + n])
            pos += n

    def tpdo_data(self, k: int) -> bytes:
        """The bytes TPDO k would carry now."""
        return b"".join(self.node.get_data(index, sub) for index, sub, _ in
                        self.mapping(0x1A00 + k))

    def send_tpdo(self, k: int) -> None:
        """Send TPDO k (if enabled) now."""
        cob = self.value(0x1800 + k, 1)
        if cob & 0x8000_0000:
            return
        self.network.send_message(cob & 0x7FF, self.tpdo_data(k))
        self.sent_tpdos += 1

    def _tpdos(self) -> list[int]:
        return [k for k in range(4) if 0x1800 + k in self.node.object_dictionary]

    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if not self.operational:
            return
        self._sync_count += 1
        # the frame's age on the wall clock, carried over to this node's clock
        age_ns = max(0.0, time.time() - timestamp) * 1e9 if timestamp else 0.0
        self._sample_ns.t = self.clock.now_ns() - int(age_ns)
        try:
            for k in self._tpdos():
                kind = self.value(0x1800 + k, 2)
                if 1 <= kind <= 240 and self._sync_count % kind == 0:
                    self.send_tpdo(k)
        finally:
            self._sample_ns.t = None

    def _on_master_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        with self._consumer_lock:
            self._master_seen_ns = self.clock.now_ns()

    def _monitor(self) -> None:
        next_cyclic: dict[int, float] = {}
        while not self._stop.wait(0.001):
            with self._consumer_lock:
                seen, limit = self._master_seen_ns, self._consumer_ms
            if limit and seen is not None and self.clock.now_ns() - seen > limit * 1e6:
                with self._consumer_lock:
                    self._master_seen_ns = None  # report once until the master is back
                with self._lock:
                    self.on_master_lost()
            now = time.monotonic()
            if self.operational:
                for k in self._tpdos():
                    period = self.cyclic_period_ms(k)
                    if period <= 0:
                        next_cyclic.pop(k, None)
                        continue
                    due = next_cyclic.setdefault(k, now)
                    if now >= due:
                        with self._lock:
                            self.send_tpdo(k)
                        next_cyclic[k] = max(due + period / 1000, now)
            with self._lock:
                self.poll()

    def cyclic_period_ms(self, k: int) -> int:
        """Event-timer period of TPDO k when its type is 0xFE/0xFF (0 = not cyclic)."""
        if self.value(0x1800 + k, 2) < 0xFE:
            return 0
        return self.value(0x1800 + k, 5)

    def emcy(self, code: int, register: int = 0x01, data: bytes = b"\x00" * 5) -> None:
        """Send an EMCY frame: code (u16), error register (u8), 5 manufacturer bytes."""
        self.store(0x1001, 0, register if code else 0)
        self.network.send_message(0x80 + self.node_id,
                                  struct.pack("<HB", code, register if code else 0) + data[:5])

    def close(self) -> None:
        """Stop the threads and leave the bus. Idempotent."""
        self._stop.set()
        for t in self._threads:
            if t is not threading.current_thread():
                t.join(timeout=2)
        self._threads.clear()
        with contextlib.suppress(Exception):
            self.node.nmt.stop_heartbeat()
        with contextlib.suppress(Exception):
            self.network.disconnect()

    def __enter__(self) -> EmulatedNode:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


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
        """Statusword, position and velocity are live."""
        now = self.clock.now_ns()
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
