"""A SCIP 2.0 sensor emulator that speaks the protocol byte for byte.

:class:`ScipSensor` is the device (a :class:`~calstation.testing.transports.StreamDevice`); put it
behind :class:`~calstation.testing.transports.TcpServer` or
:class:`~calstation.testing.transports.PtyServer`. Its ranges come from a *scene*: a callable
``scene(t_ns) -> LidarLine`` giving one line of the world at host time ``t_ns`` — the simulated
station's ``SimulatedStation.scan_line`` (real time), or :class:`WallScene` for protocol tests.

The emulated device (defaults of :class:`ScipParameters`, see docs/drivers.md):

- ARES 5000 steps per turn (0.072° per step), AMIN 2000, AMAX 3000, AFRT 2500: 1001 steps
  covering 72° centred on the front — the simulated station's field of view;
- SCAN 6000 rpm: one scan every 10 ms (100 lines/s), 2 µs per step;
- DMIN 20 mm, DMAX 30000 mm; a step with no return reports the error value 1.

Step k looks at the calstation azimuth ``α = azimuth_sign·(k − AFRT)·2π/ARES`` (the same
mapping as the driver's default; ``azimuth_sign = −1`` because Hokuyo counts counter-clockwise
seen from the sensor's top and calstation's α turns toward +X_L) and is measured at
``scan start + (k − AMIN)·60/(SCAN·ARES)`` seconds.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from calstation.drivers import LidarLine

from . import scip

Scene = Callable[[int], LidarLine]
"""``scene(t_ns) -> LidarLine``: the world as a line scanner would see it at host time t_ns."""

NO_ECHO = 1
"""Range value the emulator reports for a step without a return (below DMIN: an error code)."""

CATCH_UP_S = 10.0
"""A streamed scan the emulator could not compute in time (its thread starved on a loaded host)
is sent late, in order, if it is at most this old: the device it stands for measures every scan
on time, so a late scan is the emulator's, not the sensor's. Older ones are skipped."""

SCANS_PER_POLL = 25
"""At most this many owed scans are computed in one :meth:`ScipSensor.poll` (the lock is held
meanwhile); the rest follow in the next polls."""


@dataclass(frozen=True)
class ScipParameters:
    """What the emulated device reports in VV/PP and how it scans."""

    vendor: str = "Hokuyo Automatic Co., Ltd."
    product: str = "calstation SCIP 2.0 emulator"
    model: str = "EMU-72"
    firmware: str = "1.0.0"
    serial: str = "EMU00001"
    dmin_mm: int = 20
    dmax_mm: int = 30000
    ares: int = 5000
    amin: int = 2000
    amax: int = 3000
    afrt: int = 2500
    scan_rpm: int = 6000
    azimuth_sign: int = -1
    sensor_clock_start_ms: int = 0
    """Sensor time (ms) at power-on; set near 2^24 to test the wrap."""
    clock_drift_ppm: float = 0.0
    """Sensor clock runs fast by this many parts per million."""

    @property
    def scan_period_s(self) -> float:
        """Seconds per mirror turn (one scan)."""
        return 60.0 / self.scan_rpm

    def step_azimuths(self, start: int, end: int) -> NDArray[np.float64]:
        """(end−start+1,) calstation azimuths (rad) of steps start..end."""
        k = np.arange(start, end + 1, dtype=np.float64)
        return self.azimuth_sign * (k - self.afrt) * 2.0 * math.pi / self.ares


class WallScene:
    """A flat wall ``distance_m`` in front of the sensor (perpendicular to the boresight).

    A stand-in scene for protocol tests: range = distance / cos α, no returns beyond ``max_m``.
    """

    def __init__(self, distance_m: float = 2.0, max_m: float = 30.0) -> None:
        self.distance_m = distance_m
        self.max_m = max_m
        self._az = np.linspace(-math.pi / 2 + 0.01, math.pi / 2 - 0.01, 20001)

    def __call__(self, t_ns: int) -> LidarLine:
        """One line at ``t_ns`` (host ns)."""
        rng = self.distance_m / np.cos(self._az)
        return LidarLine(
            timestamp_ns=t_ns,
            azimuth_rad=self._az.copy(),
            range_m=rng,
            valid=rng <= self.max_m,
        )


@dataclass
class Faults:
    """Faults a test injects into the emulated sensor."""

    laser_malfunction: bool = False
    """BM answers 01 and the laser stays off."""
    corrupt_next_reply: bool = False
    """Flip one character of the next data reply (its sum no longer matches)."""
    silent: bool = False
    """Swallow every request and send nothing (a hung sensor)."""


@dataclass
class _Stream:
    """An active MD/MS request."""

    echo_head: bytes  # the request without its remaining-scans field
    chars: int
    start: int
    end: int
    cluster: int
    skip: int  # scans skipped between two sent
    remaining: int  # 0 = endless
    next_scan: int  # index of the next scan on the sensor's scan grid
    string: bytes  # the optional ";string" part of the request


class ScipSensor:
    """The emulated SCIP 2.0 sensor: command handling, laser, clock and streaming.

    Thread-safe: the transport thread calls :meth:`receive` / :meth:`poll`; tests may change
    :attr:`faults` and :attr:`scene` from another thread.
    """

    def __init__(
        self,
        scene: Scene | None = None,
        params: ScipParameters | None = None,
        *,
        now_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        self.scene: Scene = scene if scene is not None else WallScene()
        self.params = params or ScipParameters()
        self.faults = Faults()
        self._now_ns = now_ns
        self._lock = threading.RLock()
        self._boot_ns = now_ns()
        self._buffer = b""
        self.laser_on = False
        self.time_adjust = False
        self._stream: _Stream | None = None
        self.requests: list[bytes] = []
        """Every request line received (without its terminator), for tests."""
        self.scans_sent = 0

    # --- clock -----------------------------------------------------------------------------
    def sensor_ms_at(self, t_ns: int) -> int:
        """The sensor's 24-bit millisecond clock at host time ``t_ns``."""
        elapsed_ms = (t_ns - self._boot_ns) / 1e6 * (1.0 + self.params.clock_drift_ppm * 1e-6)
        return math.floor(self.params.sensor_clock_start_ms + elapsed_ms) % (
            scip.TIMESTAMP_WRAP_MS
        )

    def _scan_start_ns(self, index: int) -> int:
        """Host time of scan ``index`` on the mirror's grid (scan 0 starts at power-on)."""
        return self._boot_ns + round(index * self.params.scan_period_s * 1e9)

    def _scan_index_after(self, t_ns: int) -> int:
        return math.ceil((t_ns - self._boot_ns) / (self.params.scan_period_s * 1e9))

    # --- transport interface ---------------------------------------------------------------
    def receive(self, data: bytes) -> bytes:
        """Handle request bytes; returns the replies to send."""
        out = b""
        with self._lock:
            self._buffer += data
            while True:
                cut = min((i for i in (self._buffer.find(b"\n"), self._buffer.find(b"\r"))
                           if i >= 0), default=-1)
                if cut < 0:
                    break
                line, self._buffer = self._buffer[:cut], self._buffer[cut + 1 :]
                if not line:
                    continue  # the LF of a CRLF pair, or an empty line
                self.requests.append(line)
                if self.faults.silent:
                    continue
                out += self._handle(line)
        return out

    def poll(self) -> bytes:
        """Streamed scans that are due now."""
        with self._lock:
            if self._stream is None or self.faults.silent:
                return b""
            out = b""
            now = self._now_ns()
            st = self._stream
            # a scan is sent once the mirror has finished it; one owed for longer than
            # CATCH_UP_S is skipped, on the request's grid of scans
            latest = self._scan_index_after(now) - 2
            oldest = latest - math.ceil(CATCH_UP_S / self.params.scan_period_s)
            if st.next_scan < oldest:
                st.next_scan += (oldest - st.next_scan + st.skip) // (st.skip + 1) * (st.skip + 1)
            for _ in range(SCANS_PER_POLL):
                if self._stream is None or st.next_scan > latest:
                    break
                out += self._stream_scan(st)
            return out

    def disconnect(self) -> None:
        """The host went away: stop streaming (the laser keeps its state)."""
        with self._lock:
            self._stream = None
            self._buffer = b""

    # --- commands --------------------------------------------------------------------------
    def _handle(self, line: bytes) -> bytes:
        command = line.partition(b";")[0]
        name = command[:2]
        handler = {
            b"VV": self._vv,
            b"PP": self._pp,
            b"II": self._ii,
            b"BM": self._bm,
            b"QT": self._qt,
            b"RS": self._rs,
            b"TM": self._tm,
            b"GD": self._get,
            b"GS": self._get,
            b"MD": self._multi,
            b"MS": self._multi,
        }.get(name)
        if handler is None:
            return scip.reply(line, "0D")
        if self._stream is not None and name not in (b"QT", b"RS"):
            return scip.reply(line, "0E")
        return handler(line, command)

    def _vv(self, line: bytes, command: bytes) -> bytes:
        if command != b"VV":
            return scip.reply(line, "0C")
        p = self.params
        body = (
            scip.kv_line("VEND", p.vendor)
            + scip.kv_line("PROD", p.product)
            + scip.kv_line("FIRM", p.firmware)
            + scip.kv_line("PROT", "SCIP 2.0")
            + scip.kv_line("SERI", p.serial)
        )
        return scip.reply(line, "00", body)

    def _pp(self, line: bytes, command: bytes) -> bytes:
        if command != b"PP":
            return scip.reply(line, "0C")
        p = self.params
        body = (
            scip.kv_line("MODL", p.model)
            + scip.kv_line("DMIN", str(p.dmin_mm))
            + scip.kv_line("DMAX", str(p.dmax_mm))
            + scip.kv_line("ARES", str(p.ares))
            + scip.kv_line("AMIN", str(p.amin))
            + scip.kv_line("AMAX", str(p.amax))
            + scip.kv_line("AFRT", str(p.afrt))
            + scip.kv_line("SCAN", str(p.scan_rpm))
        )
        return scip.reply(line, "00", body)

    def _ii(self, line: bytes, command: bytes) -> bytes:
        if command != b"II":
            return scip.reply(line, "0C")
        p = self.params
        now_ms = self.sensor_ms_at(self._now_ns())
        body = (
            scip.kv_line("MODL", p.model)
            + scip.kv_line("LASR", "ON" if self.laser_on else "OFF")
            + scip.kv_line("SCSP", f"Initial({p.scan_rpm}[rpm])")
            + scip.kv_line("MESM", "Measuring" if self._stream else "Idle")
            + scip.kv_line("SBPS", "Ethernet 100 [Mbps]")
            + scip.kv_line("TIME", scip.encode_value(now_ms, 4).decode("ascii"))
            + scip.kv_line("STAT", "Fault" if self.faults.laser_malfunction else "Stable")
        )
        return scip.reply(line, "00", body)

    def _bm(self, line: bytes, command: bytes) -> bytes:
        if command != b"BM":
            return scip.reply(line, "0C")
        if self.faults.laser_malfunction:
            return scip.reply(line, "01")
        if self.laser_on:
            return scip.reply(line, "02")
        self.laser_on = True
        return scip.reply(line, "00")

    def _qt(self, line: bytes, command: bytes) -> bytes:
        if command != b"QT":
            return scip.reply(line, "0C")
        self._stream = None
        self.laser_on = False
        return scip.reply(line, "00")

    def _rs(self, line: bytes, command: bytes) -> bytes:
        if command != b"RS":
            return scip.reply(line, "0C")
        self._stream = None
        self.laser_on = False
        self.time_adjust = False
        return scip.reply(line, "00")

    def _tm(self, line: bytes, command: bytes) -> bytes:
        if command not in (b"TM0", b"TM1", b"TM2"):
            return scip.reply(line, "01")
        if command == b"TM0":
            if self.time_adjust:
                return scip.reply(line, "02")
            self.laser_on = False  # the sensor switches the laser off in time-adjust mode
            self.time_adjust = True
            return scip.reply(line, "00")
        if command == b"TM2":
            if not self.time_adjust:
                return scip.reply(line, "03")
            self.time_adjust = False
            return scip.reply(line, "00")
        if not self.time_adjust:
            return scip.reply(line, "0E")
        now_ms = self.sensor_ms_at(self._now_ns())
        return scip.reply(line, "00", scip.with_sum(scip.encode_value(now_ms, 4)))

    def _parse_range(self, command: bytes, lengths: tuple[int, ...]) -> tuple[int, ...] | str:
        """Parse the fixed-width decimal parameters after the 2-char name, or an error status."""
        fields: list[int] = []
        pos = 2
        if len(command) != 2 + sum(lengths):
            return "0C"
        for i, n in enumerate(lengths):
            text = command[pos : pos + n]
            pos += n
            if not text.isdigit():
                return f"0{i + 1}" if i < 7 else "0C"
            fields.append(int(text))
        return tuple(fields)

    def _check_steps(self, start: int, end: int) -> str | None:
        p = self.params
        if start < p.amin or start > p.amax:
            return "04"
        if end > p.amax or end < p.amin:
            return "04"
        if end < start:
            return "05"
        return None

    def _get(self, line: bytes, command: bytes) -> bytes:
        parsed = self._parse_range(command, (4, 4, 2))
        if isinstance(parsed, str):
            return scip.reply(line, parsed)
        start, end, cluster = parsed
        if (err := self._check_steps(start, end)) is not None:
            return scip.reply(line, err)
        if not self.laser_on:
            return scip.reply(line, "10")
        chars = 3 if command[:2] == b"GD" else 2
        # the reply carries the last complete scan
        index = self._scan_index_after(self._now_ns()) - 2
        body = self._scan_body(index, start, end, max(cluster, 1), chars)
        return scip.reply(line, "00", self._maybe_corrupt(body))

    def _multi(self, line: bytes, command: bytes) -> bytes:
        parsed = self._parse_range(command, (4, 4, 2, 1, 2))
        if isinstance(parsed, str):
            return scip.reply(line, parsed)
        start, end, cluster, skip, count = parsed
        if (err := self._check_steps(start, end)) is not None:
            return scip.reply(line, err)
        if self.faults.laser_malfunction:
            return scip.reply(line, "50")
        self.laser_on = True  # MD/MS switch the laser on by themselves
        _, sep, string = line.partition(b";")
        self._stream = _Stream(
            echo_head=command[:13],
            chars=3 if command[:2] == b"MD" else 2,
            start=start,
            end=end,
            cluster=max(cluster, 1),
            skip=skip,
            remaining=count,
            next_scan=self._scan_index_after(self._now_ns()),
            string=sep + string,
        )
        return scip.reply(line, "00")

    def _stream_scan(self, st: _Stream) -> bytes:
        index = st.next_scan
        st.next_scan += st.skip + 1
        if st.remaining:
            st.remaining -= 1
            left = st.remaining
            if left == 0:
                self._stream = None
                self.laser_on = False
        else:
            left = 0
        echo = st.echo_head + f"{left:02d}".encode("ascii") + st.string
        body = self._scan_body(index, st.start, st.end, st.cluster, st.chars)
        self.scans_sent += 1
        return scip.reply(echo, "99", self._maybe_corrupt(body))

    def _maybe_corrupt(self, body: bytes) -> bytes:
        if not self.faults.corrupt_next_reply or len(body) < 8:
            return body
        self.faults.corrupt_next_reply = False
        i = 7  # first data character after the timestamp line
        flipped = 0x30 + ((body[i] - 0x30 + 1) & 0x3F)
        return body[:i] + bytes((flipped,)) + body[i + 1 :]

    # --- scan data -------------------------------------------------------------------------
    def scan_ranges_mm(self, index: int, start: int, end: int) -> NDArray[np.int64]:
        """(end−start+1,) range values (mm, or :data:`NO_ECHO`) of scan ``index``."""
        p = self.params
        t0 = self._scan_start_ns(index)
        # the scan starts at AMIN; the requested window starts later
        t_first = t0 + round((start - p.amin) * p.scan_period_s / p.ares * 1e9)
        line = self.scene(t_first)
        want = p.step_azimuths(start, end)
        order = np.argsort(line.azimuth_rad)
        az = line.azimuth_rad[order]
        rng = np.asarray(line.range_m, dtype=np.float64)[order]
        ok = np.asarray(line.valid, dtype=bool)[order]
        if len(az) == len(want) and np.allclose(az, np.sort(want), atol=1e-9):
            pick = np.argsort(np.argsort(want))  # same azimuths: take them one to one
        else:  # nearest scene point for each step (keeps depth edges sharp)
            idx = np.clip(np.searchsorted(az, want), 1, len(az) - 1)
            left_closer = np.abs(want - az[idx - 1]) <= np.abs(az[idx] - want)
            pick = np.where(left_closer, idx - 1, idx)
        r_mm = np.round(rng[pick] * 1000.0)
        good = ok[pick] & np.isfinite(r_mm) & (r_mm >= p.dmin_mm) & (r_mm <= p.dmax_mm)
        out = np.full(len(want), NO_ECHO, dtype=np.int64)
        out[good] = r_mm[good].astype(np.int64)
        return out

    def _scan_body(self, index: int, start: int, end: int, cluster: int, chars: int) -> bytes:
        values = self.scan_ranges_mm(index, start, end)
        if cluster > 1:  # a cluster reports its smallest valid range
            n = math.ceil(len(values) / cluster)
            padded = np.full(n * cluster, np.iinfo(np.int64).max, dtype=np.int64)
            padded[: len(values)] = np.where(values >= self.params.dmin_mm, values, padded[0])
            values = padded.reshape(n, cluster).min(axis=1)
            values[values == np.iinfo(np.int64).max] = NO_ECHO
        if chars == 2:
            values = np.where(values > 4095, NO_ECHO, values)
        stamp = scip.encode_value(self.sensor_ms_at(self._scan_start_ns(index)), 4)
        return scip.with_sum(stamp) + scip.data_lines(scip.encode_values(values, chars))
