"""One CANopen network per bus, shared by the drivers of a run; SYNC and heartbeat producers.

The turntable and the encoder usually sit on one CAN bus. Both drivers get the same
:class:`SharedBus` from ``context.shared["canopen"]`` (keyed by interface and channel), so there is
one ``canopen.Network``, one SYNC producer and one master heartbeat. The SYNC producer is a thread
of ours rather than python-can's periodic task because the encoder driver needs the host time
of every SYNC it sent: a CiA 406 encoder on transmission type 1 samples its position at the SYNC.
"""

from __future__ import annotations

import bisect
import contextlib
import logging
import struct
import threading
import time
from collections import deque
from collections.abc import Iterator, Mapping
from typing import Any, Protocol

import can
import canopen

from calstation.clock import Clock, HostClock
from calstation.drivers import DriverContext
from calstation.errors import DeviceTimeout, DriverError

log = logging.getLogger(__name__)

SYNC_COB_ID = 0x080
NMT_COB_ID = 0x000


class CanopenError(DriverError):
    """A CANopen device could not be talked to, or reported a fault."""


class CanopenTimeout(CanopenError, DeviceTimeout):
    """A CANopen device did not answer (SDO) or did not reach a state in time."""


MAX_TPDO_DELAY_S = 0.05
"""A synchronous TPDO answering later than this (and than two SYNC periods) counts as lost."""

WALL_CLOCK_STAMPS = frozenset({"socketcan", "virtual"})
"""The python-can interfaces whose frame timestamps are the host's wall clock."""

SYNC_SEND_S = 0.001
"""A SYNC whose sending took longer than this has an uncertain time: the host's thread was held
between reading the clock and the frame reaching the bus (a busy host), and the devices latched
their inputs up to that long after the time on record. What they latched at it is dropped
(:meth:`SharedBus.sync_time_certain`), not stamped that far off."""

MAX_FRAME_AGE_S = 10.0
"""A received frame's timestamp older than this (or in the future) is not on the wall clock:
the interface's timestamps are not used."""


class _Periodic(Protocol):
    """A message canopen sends periodically (its ``PeriodicMessageTask``)."""

    def stop(self) -> None:
        """Stop sending it."""
        ...


class SharedBus:
    """A connected ``canopen.Network`` plus a SYNC producer that remembers when it sent SYNCs."""

    def __init__(
        self, interface: str, channel: str, bitrate: int = 500_000, clock: Clock | None = None
    ) -> None:
        self.interface = interface
        self.channel = channel
        self.clock: Clock = clock or HostClock()
        self.network = canopen.Network()
        kwargs: dict[str, str | int] = {"interface": interface, "channel": channel}
        if interface not in ("virtual", "udp_multicast"):
            kwargs["bitrate"] = bitrate
        try:
            self.network.connect(**kwargs)
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            raise CanopenError(
                f"canopen: cannot open CAN bus {interface}:{channel}: {exc}"
            ) from exc
        self.users = 0
        self._sync_times: deque[int] = deque(maxlen=4096)
        self._uncertain_syncs: deque[int] = deque(maxlen=64)
        self._sync_lock = threading.Lock()
        self._sync_stop = threading.Event()
        self._sync_thread: threading.Thread | None = None
        self.sync_period_s = 0.0
        self._heartbeat: _Periodic | None = None

    # --- SYNC ------------------------------------------------------------------------------
    def start_sync(self, period_s: float) -> None:
        """Send SYNC every ``period_s``; the shortest period any user asked for wins."""
        if period_s <= 0 or (self._sync_thread is not None and period_s >= self.sync_period_s):
            return
        self.stop_sync()
        self.sync_period_s = period_s
        self._sync_stop.clear()
        self._sync_thread = threading.Thread(target=self._sync_loop, name="canopen-sync",
                                             daemon=True)
        self._sync_thread.start()

    def _sync_loop(self) -> None:
        period_ns = round(self.sync_period_s * 1e9)
        next_ns = self.clock.now_ns()
        while not self._sync_stop.is_set():
            now = self.clock.now_ns()
            if now < next_ns:
                self._sync_stop.wait((next_ns - now) / 1e9)
                continue
            sent = self.send_sync()
            next_ns += period_ns
            # fell behind (a busy machine): no burst. Two SYNCs closer than the devices take to
            # answer cannot be told apart by their answers' time on the wire (at a load of
            # twice the cores, SYNCs 0.1 ms apart had answers paired one SYNC off, then each
            # answer after them, 10 to 30 ms from the count they carried)
            if next_ns < sent + period_ns // 2:
                next_ns = sent + period_ns

    def send_sync(self) -> int:
        """Send one SYNC now; returns its host time (ns)."""
        # sending and recording under one lock: a TPDO answering this SYNC cannot be paired
        # before the SYNC's time is on record
        with self._sync_lock:
            t = self.clock.now_ns()
            try:
                self.network.send_message(SYNC_COB_ID, b"")
            except can.CanError as exc:
                log.warning("canopen: SYNC not sent: %s", exc)
                return t
            if self.clock.now_ns() - t > SYNC_SEND_S * 1e9:
                self._uncertain_syncs.append(t)
            self._sync_times.append(t)
        return t

    def sync_time_certain(self, t_ns: int) -> bool:
        """Whether the SYNC sent at ``t_ns`` reached the bus within :data:`SYNC_SEND_S` of that
        time (what a device latched at it is then stamped with it)."""
        with self._sync_lock:
            return t_ns not in self._uncertain_syncs

    def stop_sync(self) -> None:
        """Stop the SYNC producer."""
        self._sync_stop.set()
        thread, self._sync_thread = self._sync_thread, None
        if thread is not None:
            thread.join(timeout=2)

    def wire_ns(self, timestamp: float, now_ns: int) -> int | None:
        """A frame's time on the wire, in the host clock of ``now_ns`` (when it is handled):
        python-can's ``timestamp`` (seconds since the epoch: the kernel's time of reception on
        socketcan, the sender's on a virtual bus) carried over by the frame's age. None on
        other interfaces (their stamps come from the adapter's own clock, mapped to the host's
        with an offset of their own), and when the stamp is not on the wall clock
        (:data:`MAX_FRAME_AGE_S`)."""
        if self.interface not in WALL_CLOCK_STAMPS or not timestamp or timestamp <= 0:
            return None
        age = time.time() - timestamp
        if not -0.001 <= age <= MAX_FRAME_AGE_S:
            return None
        return now_ns - round(max(age, 0.0) * 1e9)

    def pair_sync(self, after_ns: int, now_ns: int, wire_ns: int | None = None) -> int | None:
        """The host time of the SYNC a synchronous TPDO handled at ``now_ns`` answers.

        With the frame's time on the wire (``wire_ns``, :meth:`wire_ns`): the last SYNC sent
        before it, when that is after ``after_ns`` (the previous pairing), else None: a frame
        cannot answer a SYNC sent after it was on the wire, and one whose SYNC was already
        answered is not stamped with another's time. A device answers a SYNC within a fraction
        of its period, so this holds however late the host handles the frame, and a lost
        answer shifts nothing after it.

        Else, by order: the oldest SYNC sent after ``after_ns`` — devices answer SYNCs in
        order — unless it is older than :data:`MAX_TPDO_DELAY_S` or two periods, whichever is
        longer (its TPDO was lost): then the newest. None if no SYNC was sent after
        ``after_ns``. The floor keeps pairing in order on a busy host, where an answer can lag
        by several SYNC periods without being lost."""
        with self._sync_lock:
            times = list(self._sync_times)
        if wire_ns is not None:
            i = bisect.bisect_right(times, wire_ns)
            return times[i - 1] if i and times[i - 1] > after_ns else None
        pending = times[bisect.bisect_right(times, after_ns) : bisect.bisect_right(times, now_ns)]
        if not pending:
            return None
        if now_ns - pending[0] <= max(2 * self.sync_period_s, MAX_TPDO_DELAY_S) * 1e9:
            return pending[0]
        return pending[-1]

    # --- master heartbeat ------------------------------------------------------------------
    def start_heartbeat(self, master_id: int, period_s: float) -> None:
        """Produce the master's heartbeat (state operational, 0x05) on 0x700 + master_id."""
        if self._heartbeat is None and period_s > 0:
            self._heartbeat = self.network.send_periodic(0x700 + master_id, bytes([0x05]), period_s)

    def stop_heartbeat(self) -> None:
        """Stop the master heartbeat (drives that consume it will fault: use on purpose only)."""
        task, self._heartbeat = self._heartbeat, None
        if task is not None:
            with contextlib.suppress(Exception):
                task.stop()

    def close(self) -> None:
        """Stop producers and disconnect. Idempotent."""
        self.stop_sync()
        self.stop_heartbeat()
        with contextlib.suppress(Exception):
            self.network.disconnect()


def acquire_bus(
    settings: Mapping[str, Any], context: DriverContext | None  # Any: the recipe's settings
) -> SharedBus:
    """The run's :class:`SharedBus` for ``settings['interface']``/``['channel']`` (created on
    first use); release it with :func:`release_bus`."""
    interface = str(settings.get("interface", "socketcan"))
    channel = settings.get("channel")
    if not channel:
        raise CanopenError(
            "canopen driver: settings.channel is required (e.g. can0 for socketcan, any name for "
            "the virtual interface, a multicast group for udp_multicast)"
        )
    key = f"{interface}:{channel}"
    clock = context.clock if context is not None else None
    if context is None:
        bus = SharedBus(interface, str(channel), int(settings.get("bitrate", 500_000)), clock)
    else:
        buses: dict[str, SharedBus] = context.shared.setdefault("canopen", {})
        bus = buses.get(key) or SharedBus(
            interface, str(channel), int(settings.get("bitrate", 500_000)), clock
        )
        buses[key] = bus
    bus.users += 1
    return bus


class BusNodeDriver:
    """What the CANopen drivers share: the run's :class:`SharedBus`, one remote node on it, and
    expedited SDO access to that node (errors name ``driver_name`` and the node)."""

    driver_name: str = "canopen"
    context: DriverContext | None
    clock: Clock
    node_id: int
    bus: SharedBus
    network: canopen.Network
    node: canopen.RemoteNode

    def _attach_node(
        self, settings: Mapping[str, Any], context: DriverContext | None  # Any: as acquire_bus
    ) -> None:
        """Take the run's bus (:func:`acquire_bus`; release it with :func:`release_bus`) and add
        the remote node ``settings['node_id']``, awaiting its SDO responses for
        ``settings['sdo_timeout_s']`` (s). Stamps come from ``context.clock`` (the host clock
        without a context)."""
        self.context = context
        self.clock = context.clock if context is not None else HostClock()
        self.node_id = int(settings["node_id"])
        self.bus = acquire_bus(settings, context)
        self.network = self.bus.network
        # canopen's ObjectDictionary has no annotations; an empty one: the driver reads and
        # writes by index and subindex
        dictionary = canopen.ObjectDictionary()  # type: ignore[no-untyped-call]
        self.node = canopen.RemoteNode(self.node_id, dictionary)
        self.network.add_node(self.node)
        self.node.sdo.RESPONSE_TIMEOUT = float(settings["sdo_timeout_s"])

    @contextlib.contextmanager
    def _sdo_errors(self, action: str, index: int, sub: int, detail: str = "") -> Iterator[None]:
        """Turn canopen's SDO errors into calstation's, naming the node, the entry and
        ``action`` ("writing" or "reading")."""
        entry = f"0x{index:04X}:{sub:02X}"
        try:
            yield
        except canopen.SdoAbortedError as exc:
            raise CanopenError(
                f"{self.driver_name} node {self.node_id}: {action} {entry}{detail} was "
                f"refused ({exc})"
            ) from exc
        except canopen.SdoCommunicationError as exc:
            raise CanopenTimeout(
                f"{self.driver_name} node {self.node_id}: no SDO answer {action} {entry} ({exc})"
            ) from exc

    def sdo_write(self, index: int, sub: int, fmt: str, value: int) -> None:
        """Expedited SDO download (``fmt`` a struct code: <B, <H, <I, <b, <i)."""
        with self._sdo_errors("writing", index, sub, f" = {value}"):
            self.node.sdo.download(index, sub, struct.pack(fmt, value))

    def sdo_read(self, index: int, sub: int, fmt: str) -> int:
        """Expedited SDO upload, decoded with ``fmt``."""
        with self._sdo_errors("reading", index, sub):
            data = self.node.sdo.upload(index, sub)
        return int(struct.unpack(fmt, data[: struct.calcsize(fmt)])[0])


def release_bus(bus: SharedBus, context: DriverContext | None) -> None:
    """Drop one user of ``bus``; the last one closes it."""
    bus.users -= 1
    if bus.users > 0:
        return
    bus.close()
    if context is not None:
        buses = context.shared.get("canopen", {})
        for key, value in list(buses.items()):
            if value is bus:
                del buses[key]
