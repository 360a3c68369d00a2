"""The ``canopen406`` encoder driver: a CiA 406 rotary encoder on CANopen.

Start-up: NMT pre-operational; read 0x6001 (measuring units per revolution) and 0x6002 (total
measuring range, where the position value wraps); map TPDO1 = position value 0x6004 (32 bits),
transmission type 0x01 (sampled at every SYNC, ``mode: sync``) or 0xFE with cyclic timer 0x6200
(``mode: cyclic``); NMT start. Each TPDO becomes an :class:`~calstation.drivers.EncoderSample`:

- ``mode: sync``: stamped with the host time at which the driver sent the SYNC that sampled it
  (the encoder latches its position at the SYNC; paired by the frame's time on the wire when
  the interface gives it, :meth:`~calstation_canopen.bus.SharedBus.pair_sync`); none from a
  SYNC that took the host longer than ``SYNC_SEND_S`` to send (its time is uncertain), and none
  from a TPDO no SYNC of its own can be paired with (when it latched is not known);
- ``mode: cyclic``: stamped with the host time of reception (on the wire, when the interface
  gives it).

``latency_s`` is subtracted from every stamp. The raw position is unwrapped into a signed count
(steps of more than half the measuring range are taken as a wrap).
"""

from __future__ import annotations

import contextlib
import logging
import struct
import threading
from collections.abc import Mapping

from calstation.drivers import DriverContext, EncoderSample

from .bus import BusNodeDriver, CanopenError, CanopenTimeout, release_bus
from .drive import check_settings

log = logging.getLogger(__name__)

SETTINGS_DEFAULTS: dict[str, object] = {
    "interface": "socketcan",
    "channel": None,
    "bitrate": 500_000,
    "node_id": 2,
    "mode": "sync",
    "sync_period_s": 0.002,
    "cyclic_ms": 2,
    "counts_per_revolution": None,
    "latency_s": 0.0,
    "sdo_timeout_s": 0.5,
    "emulate": False,
}
"""Recipe ``settings`` of the ``canopen406`` driver and their defaults (docs/drivers.md)."""


class Unwrapper:
    """Raw positions that wrap at ``total_range`` → a signed, continuous count."""

    def __init__(self, total_range: int) -> None:
        self.total_range = total_range
        self._last_raw: int | None = None
        self.count = 0

    def __call__(self, raw: int) -> int:
        """The unwrapped count of ``raw``."""
        if self._last_raw is None:
            # the first reading: positions past half the range are negative counts
            self.count = raw - self.total_range if raw >= self.total_range // 2 else raw
        else:
            d = (raw - self._last_raw) % self.total_range
            if d >= self.total_range // 2:
                d -= self.total_range
            self.count += d
        self._last_raw = raw
        return self.count


class Cia406Encoder(BusNodeDriver):
    """A CiA 406 encoder behind calstation's :class:`~calstation.drivers.Encoder` protocol."""

    driver_name = "canopen406"

    def __init__(
        self, settings: Mapping[str, object], context: DriverContext | None = None
    ) -> None:
        self.settings = check_settings("canopen406", settings, SETTINGS_DEFAULTS)
        if self.settings["mode"] not in ("sync", "cyclic"):
            raise CanopenError(
                f"canopen406 driver: settings.mode must be 'sync' or 'cyclic', not "
                f"{self.settings['mode']!r}"
            )
        self._attach_node(self.settings, context)
        self._lock = threading.Lock()
        self._samples: list[EncoderSample] = []
        self._latest: EncoderSample | None = None
        self._new = threading.Condition(self._lock)
        self._closed = False
        self._last_sync_ns = 0
        try:
            self._start()
        except BaseException:
            release_bus(self.bus, context)
            raise

    def _start(self) -> None:
        s = self.settings
        n = self.node_id
        self.node.nmt.state = "PRE-OPERATIONAL"
        cpr = self.sdo_read(0x6001, 0, "<I")
        if s["counts_per_revolution"] is not None and int(s["counts_per_revolution"]) != cpr:
            raise CanopenError(
                f"canopen406 node {n}: settings.counts_per_revolution = "
                f"{s['counts_per_revolution']} but the encoder reports {cpr} (0x6001)"
            )
        self._cpr = cpr
        try:
            total = self.sdo_read(0x6002, 0, "<I") or (1 << 32)
        except CanopenError:
            total = 1 << 32
        self.unwrap = Unwrapper(total)
        sync = s["mode"] == "sync"
        self.sdo_write(0x1800, 1, "<I", 0x8000_0000 | (0x180 + n))
        self.sdo_write(0x1A00, 0, "<B", 0)
        self.sdo_write(0x1A00, 1, "<I", 0x60040020)
        self.sdo_write(0x1A00, 0, "<B", 1)
        self.sdo_write(0x1800, 2, "<B", 0x01 if sync else 0xFE)
        if not sync:
            self.sdo_write(0x6200, 0, "<H", int(s["cyclic_ms"]))
        self.sdo_write(0x1800, 1, "<I", 0x180 + n)
        self.network.subscribe(0x180 + n, self._on_tpdo)
        if sync:
            self.bus.start_sync(float(s["sync_period_s"]))
        # SYNCs sent before the encoder is operational are never answered
        self._last_sync_ns = self.clock.now_ns()
        self.node.nmt.state = "OPERATIONAL"

    def _on_tpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if len(data) < 4:
            return
        now = self.clock.now_ns()
        raw = struct.unpack_from("<I", data)[0]
        wire = self.bus.wire_ns(timestamp, now)
        t = now if wire is None else wire
        if self.settings["mode"] == "sync":
            t_sync = self.bus.pair_sync(self._last_sync_ns, now, wire)
            if t_sync is None:
                return  # no SYNC of its own to be stamped with: when it latched is not known
            t = self._last_sync_ns = t_sync
            if not self.bus.sync_time_certain(t_sync):
                return  # latched up to a host's stall after that time: not stamped with it
        t -= round(float(self.settings["latency_s"]) * 1e9)
        with self._new:
            sample = EncoderSample(timestamp_ns=t, count=self.unwrap(raw))
            self._samples.append(sample)
            self._latest = sample
            self._new.notify_all()

    def info(self) -> dict[str, str | int]:
        """Identity read by SDO: node id, device type 0x1000, resolution and range."""
        return {
            "protocol": "CANopen CiA 406",
            "bus": f"{self.bus.interface}:{self.bus.channel}",
            "node_id": self.node_id,
            "device_type": f"0x{self.sdo_read(0x1000, 0, '<I'):08X}",
            "counts_per_revolution": self._cpr,
            "total_measuring_range": self.unwrap.total_range,
            "mode": self.settings["mode"],
        }

    @property
    def counts_per_revolution(self) -> int:
        """0x6001 measuring units per revolution."""
        return self._cpr

    def read(self, timeout_s: float = 1.0) -> EncoderSample:
        """The next sample from the stream (waits up to ``timeout_s``)."""
        with self._new:
            before = self._latest
            if not self._new.wait_for(lambda: self._latest is not before, timeout=timeout_s):
                raise CanopenTimeout(
                    f"canopen406 node {self.node_id}: no position TPDO for {timeout_s:g} s"
                )
            assert self._latest is not None
            return self._latest

    def samples(self) -> list[EncoderSample]:
        """Every sample since the previous call, oldest first."""
        with self._lock:
            out, self._samples = self._samples, []
        return out

    def close(self) -> None:
        """Stop the TPDO stream and release the bus. Idempotent."""
        if self._closed:
            return
        self._closed = True
        with contextlib.suppress(Exception):
            self.network.unsubscribe(0x180 + self.node_id, self._on_tpdo)
        with contextlib.suppress(Exception):
            self.node.nmt.state = "PRE-OPERATIONAL"
        release_bus(self.bus, self.context)
