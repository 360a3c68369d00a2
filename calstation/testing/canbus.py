# The canopen package has no type hints and its object dictionary entries are a union that
# mypy cannot index; the checks that depend on them are relaxed for this module only.
# mypy: disable-error-code="no-untyped-call, index"
"""An emulated CANopen node on python-can, for driver tests without hardware.

:class:`EmulatedNode` is a ``canopen.LocalNode`` (its SDO server and NMT slave come from the
``canopen`` package) on a network of its own, connected to the CAN channel the driver under test
uses (python-can's ``virtual`` interface in one process, ``udp_multicast`` across processes). It
adds what LocalNode leaves out:

- received RPDOs are decoded with the node's own mapping (0x1600+k) and written into the object
  dictionary through ``set_data``, so the write callbacks (a device state machine) see them;
- TPDOs are built from the mapping (0x1A00+k) on SYNC (transmission type 1..240) or cyclically
  (0xFE with an event timer), reading live values through read callbacks;
- the heartbeat consumer (0x1016) calls :meth:`EmulatedNode.on_master_lost` when the master goes
  silent.

A device emulator subclasses it: :meth:`~EmulatedNode.build_od` adds the profile's objects
(helpers :func:`add_variable`, :func:`add_record`, :func:`add_pdo_objects`),
:meth:`~EmulatedNode.on_write` reacts to writes and :meth:`~EmulatedNode.on_read` gives live
values. The CiA 402 drive and CiA 406 encoder of the ``calstation-canopen`` plugin are built so.
"""

from __future__ import annotations

import contextlib
import logging
import struct
import threading
import time
from collections.abc import Callable

import can
import canopen
from canopen.objectdictionary import ODArray, ODRecord, ODVariable, datatypes

from calstation.clock import Clock, HostClock

log = logging.getLogger(__name__)

U8, U16, U32 = datatypes.UNSIGNED8, datatypes.UNSIGNED16, datatypes.UNSIGNED32
I8, I16, I32 = datatypes.INTEGER8, datatypes.INTEGER16, datatypes.INTEGER32
_FORMATS = {U8: "<B", U16: "<H", U32: "<I", I8: "<b", I16: "<h", I32: "<i"}

SYNC_COB_ID = 0x080
"""COB-ID of the SYNC frame (CiA 301)."""
CONSUMER_HEARTBEAT = 0x1016
"""Consumer heartbeat time object (CiA 301)."""
PRODUCER_HEARTBEAT = 0x1017
"""Producer heartbeat time object (CiA 301)."""


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


ANSWER_S = 0.0002
"""How long after a SYNC an emulated device's answer is on the wire: a device answers within a
fraction of a millisecond, whenever the host gets round to running its emulator."""


class _StampedNetwork(canopen.Network):
    """An emulated device's network: every frame carries its time on the wire, set by the
    sender (a virtual bus keeps it: ``preserve_timestamps``), and a SYNC's answers the SYNC's
    own time plus :data:`ANSWER_S` (``answering``), as a device's would."""

    def __init__(self) -> None:
        super().__init__()
        self.answering = threading.local()

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        """Send a frame stamped with its time on the wire."""
        if not self.bus:
            raise RuntimeError("Not connected to CAN bus")
        stamp = getattr(self.answering, "t", None)
        msg = can.Message(is_extended_id=can_id > 0x7FF, arbitration_id=can_id, data=data,
                          is_remote_frame=remote,
                          timestamp=time.time() if stamp is None else stamp)
        with self.send_lock:
            self.bus.send(msg)
        self.check()


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
        add_variable(od, "producer heartbeat time", PRODUCER_HEARTBEAT, U16, heartbeat_ms)
        add_record(od, "consumer heartbeat time", CONSUMER_HEARTBEAT, [("consumer 1", U32, 0)],
                   array=True)
        self.build_od(od)
        self.network = _StampedNetwork()
        # a virtual bus stamps a frame when it is sent, unless told to keep the sender's stamp
        self.network.connect(interface=interface, channel=channel,
                             **({"preserve_timestamps": True} if interface == "virtual" else {}))
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
        if index == CONSUMER_HEARTBEAT and subindex == 1:
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
    def _rpdo_callbacks(self) -> list[Callable[..., None]]:
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
        self.network.answering.t = timestamp + ANSWER_S if timestamp else None
        try:
            for k in self._tpdos():
                kind = self.value(0x1800 + k, 2)
                if 1 <= kind <= 240 and self._sync_count % kind == 0:
                    self.send_tpdo(k)
        finally:
            self._sample_ns.t = None
            self.network.answering.t = None

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
