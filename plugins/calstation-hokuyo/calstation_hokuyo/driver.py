"""The Hokuyo SCIP 2.0 lidar driver (calstation's ``Lidar`` protocol) on pyserial.

It opens any pyserial URL: a serial port (``/dev/ttyACM0``), a TCP sensor
(``socket://192.168.0.10:10940``) or a pseudo-terminal. Streaming uses ``MD`` (3-character
ranges) or ``MS`` (2-character); single scans use ``GD``/``GS``.

Azimuths. Hokuyo step k lies at ``(k − AFRT)·2π/ARES`` counter-clockwise from the front, seen from
the sensor's top. calstation's α (DESIGN §2) is 0 on the +Y_L boresight and positive toward +X_L.
The driver maps ``α_k = azimuth_sign · (k − boresight_step) · 2π / ARES`` with the defaults
``azimuth_sign = −1`` (the sensor's top points along +Z_L, so counter-clockwise turns toward −X_L)
and ``boresight_step = AFRT``. Mount the sensor upside down and set ``azimuth_sign: 1``.

Time. Each scan carries a 24-bit millisecond sensor timestamp. :class:`ClockSync` estimates the
sensor→host offset from TM1 round trips (the shortest round trip of several), unwraps the 24-bit
counter and, from successive syncs, the drift. Within a stream a least-squares line through the
(scan number, timestamp) pairs removes the 1 ms quantisation (the mirror turns at a fixed rate).
"""

from __future__ import annotations

import contextlib
import logging
import math
import queue
import threading
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import serial

from calstation.clock import Clock, HostClock
from calstation.drivers import LidarInfo, LidarLine

from . import scip
from .scip import HokuyoError, Reply, ScipStatusError, ScipTimeout

log = logging.getLogger(__name__)

SETTINGS_DEFAULTS: dict[str, object] = {
    "port": None,
    "baudrate": 115200,
    "timeout_s": 1.0,
    "azimuth_sign": -1,
    "boresight_step": None,
    "start_step": None,
    "end_step": None,
    "cluster": 1,
    "encoding": "D",
    "sync_round_trips": 8,
    "reconnect_attempts": 2,
    "timestamp_offset_s": 0.0,
    "max_bad_sums": 0,
    "emulate": False,
}
"""Recipe ``settings`` of the ``hokuyo`` driver and their defaults (docs/drivers.md)."""


@dataclass(frozen=True)
class SensorParameters:
    """What PP reports: range limits (mm), step geometry and mirror speed (rpm)."""

    model: str
    dmin_mm: int
    dmax_mm: int
    ares: int
    amin: int
    amax: int
    afrt: int
    scan_rpm: int

    @classmethod
    def from_fields(cls, f: Mapping[str, str]) -> SensorParameters:
        """Parse the fields of a PP reply."""
        try:
            return cls(
                model=f.get("MODL", ""),
                dmin_mm=int(f["DMIN"]),
                dmax_mm=int(f["DMAX"]),
                ares=int(f["ARES"]),
                amin=int(f["AMIN"]),
                amax=int(f["AMAX"]),
                afrt=int(f["AFRT"]),
                scan_rpm=int(f["SCAN"].split("(")[0]),
            )
        except (KeyError, ValueError) as exc:
            raise scip.ScipProtocolError(f"PP reply lacks or garbles a field: {exc}") from exc

    @property
    def scan_period_s(self) -> float:
        """Seconds per scan."""
        return 60.0 / self.scan_rpm

    @property
    def step_period_s(self) -> float:
        """Seconds between two steps."""
        return self.scan_period_s / self.ares


@dataclass(frozen=True)
class StepMapping:
    """Hokuyo steps → calstation azimuths: ``α = sign·(k − boresight)·2π/ares`` (radians)."""

    ares: int
    boresight_step: float
    sign: int = -1

    def azimuths(self, start: int, end: int, cluster: int = 1) -> np.ndarray:
        """Azimuths (rad) of the clusters of steps start..end (a cluster's centre step)."""
        n = math.ceil((end - start + 1) / cluster)
        first = start + np.arange(n, dtype=np.float64) * cluster
        last = np.minimum(first + cluster - 1, end)
        centre = (first + last) / 2.0
        return np.asarray(self.sign * (centre - self.boresight_step) * 2.0 * math.pi / self.ares)


class ClockSync:
    """Sensor milliseconds (24-bit, wrapping) → host nanoseconds.

    ``add(host_send_ns, host_recv_ns, sensor_ms)`` feeds TM1 round trips; :meth:`commit` keeps the
    one with the shortest round trip as an anchor (the sensor read its clock somewhere inside it;
    the middle is the best guess, and the reported ms is truncated, hence +0.5 ms). Two anchors
    further apart than ``min_drift_baseline_s`` give the drift (sensor ms per host ms).
    """

    def __init__(self, min_drift_baseline_s: float = 5.0) -> None:
        self.min_drift_baseline_s = min_drift_baseline_s
        self._trips: list[tuple[int, int, int]] = []
        self.anchors: list[tuple[int, float]] = []  # (host ns, unwrapped sensor ms)
        self.rate = 1.0  # sensor ms per host ms
        self._last_raw: int | None = None
        self._last_unwrapped = 0

    def unwrap(self, raw_ms: int) -> int:
        """Unwrap a 24-bit sensor time against the previous one (nearest in the ±2^23 ms band)."""
        raw_ms = int(raw_ms) % scip.TIMESTAMP_WRAP_MS
        if self._last_raw is None:
            self._last_raw, self._last_unwrapped = raw_ms, raw_ms
            return raw_ms
        d = (raw_ms - self._last_raw) % scip.TIMESTAMP_WRAP_MS
        if d >= scip.TIMESTAMP_WRAP_MS // 2:
            d -= scip.TIMESTAMP_WRAP_MS
        self._last_raw = raw_ms
        self._last_unwrapped += d
        return self._last_unwrapped

    def add(self, host_send_ns: int, host_recv_ns: int, sensor_ms: int) -> None:
        """One TM1 round trip."""
        self._trips.append((host_send_ns, host_recv_ns, sensor_ms))

    def commit(self) -> float:
        """Make the best round trip of those added an anchor; returns its round trip (s)."""
        if not self._trips:
            raise HokuyoError("clock sync: no TM1 round trip succeeded")
        send, recv, raw = min(self._trips, key=lambda t: t[1] - t[0])
        self._trips.clear()
        unwrapped = self.unwrap(raw) + 0.5
        self.anchors.append(((send + recv) // 2, unwrapped))
        first_host, first_ms = self.anchors[0]
        host, ms = self.anchors[-1]
        if (host - first_host) / 1e9 >= self.min_drift_baseline_s:
            self.rate = (ms - first_ms) / ((host - first_host) / 1e6)
        return (recv - send) / 1e9

    @property
    def synced(self) -> bool:
        """True once an anchor exists."""
        return bool(self.anchors)

    def to_host_ns(self, unwrapped_ms: float) -> int:
        """Host ns of an unwrapped sensor time (ms)."""
        if not self.anchors:
            raise HokuyoError("clock sync: sensor time used before any TM1 round trip")
        host, ms = self.anchors[-1]
        return host + round((unwrapped_ms - ms) / self.rate * 1e6)

    @property
    def drift_ppm(self) -> float:
        """Estimated sensor clock rate error (parts per million; + = sensor fast)."""
        return (self.rate - 1.0) * 1e6


class _ScanTimeFilter:
    """Least-squares line through (scan number, sensor ms) of one stream: removes 1 ms steps."""

    def __init__(self, period_ms: float) -> None:
        self.period_ms = period_ms
        self.reset()

    def reset(self) -> None:
        self._first: float | None = None
        self._n = self._sx = self._sy = self._sxx = self._sxy = 0.0

    def __call__(self, ms: float) -> float:
        if self._first is None:
            self._first = ms
        k = round((ms - self._first) / self.period_ms)
        y = ms - self._first
        self._n += 1
        self._sx += k
        self._sy += y
        self._sxx += k * k
        self._sxy += k * y
        det = self._n * self._sxx - self._sx * self._sx
        if self._n < 3 or det <= 0:
            return ms
        b = (self._n * self._sxy - self._sx * self._sy) / det
        a = (self._sy - b * self._sx) / self._n
        fitted = a + b * k
        if abs(fitted - y) > 2.0:  # a jump (sensor reset, dropped clock): start a new line
            self.reset()
            return self(ms)
        return self._first + fitted


def _cluster_field(cluster: int) -> str:
    """The 2-digit cluster field: ``00`` for no grouping, as the spec's examples write it."""
    return "00" if cluster <= 1 else f"{cluster:02d}"


class HokuyoLidar:
    """A Hokuyo SCIP 2.0 scanner behind calstation's :class:`~calstation.drivers.Lidar` protocol.

    ``settings`` are those of :data:`SETTINGS_DEFAULTS` (``port`` is required). Lines are stamped
    on ``clock`` (host ns). Call :meth:`close` (or use it as a context manager) to stop the laser
    and release the port.
    """

    def __init__(self, settings: Mapping[str, object], clock: Clock | None = None) -> None:
        unknown = sorted(set(settings) - set(SETTINGS_DEFAULTS))
        if unknown:
            raise HokuyoError(
                f"hokuyo driver: unknown setting(s) {', '.join(unknown)}; known: "
                f"{', '.join(sorted(SETTINGS_DEFAULTS))}"
            )
        cfg: dict[str, Any] = {**SETTINGS_DEFAULTS, **settings}  # Any: converted where read
        if not cfg["port"]:
            raise HokuyoError(
                "hokuyo driver: settings.port is required (a serial port such as /dev/ttyACM0 or "
                "a URL such as socket://192.168.0.10:10940)"
            )
        if cfg["encoding"] not in ("D", "S"):
            raise HokuyoError(
                f"hokuyo driver: settings.encoding must be 'D' (3-char) or 'S' (2-char), "
                f"not {cfg['encoding']!r}"
            )
        if cfg["azimuth_sign"] not in (1, -1):
            raise HokuyoError(
                f"hokuyo driver: settings.azimuth_sign must be 1 or -1, not {cfg['azimuth_sign']!r}"
            )
        self.settings = cfg
        self.url: str = str(cfg["port"])
        self.timeout_s = float(cfg["timeout_s"])
        self.clock: Clock = clock or HostClock()
        self.sync = ClockSync()
        self._port: serial.SerialBase | None = None
        self._buf = b""
        self._io = threading.RLock()
        self._params: SensorParameters | None = None
        self._version: dict[str, str] = {}
        self._queue: queue.Queue[LidarLine | BaseException] = queue.Queue()
        self._reader: threading.Thread | None = None
        self._streaming = threading.Event()
        self._time_filter: _ScanTimeFilter | None = None
        self._azimuths: dict[tuple[int, int, int], np.ndarray] = {}
        self._stream_request = ""
        self.bad_sums = 0
        self.reconnects = 0
        self.last_round_trip_s = math.nan

    # --- connection ------------------------------------------------------------------------
    def open(self) -> None:
        """Open the port (idempotent)."""
        if self._port is not None:
            return
        try:
            self._port = serial.serial_for_url(
                self.url, baudrate=int(self.settings["baudrate"]), timeout=0
            )  # non-blocking: reads return what has arrived (pyserial's socket in_waiting is 0/1)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise HokuyoError(f"hokuyo: cannot open {self.url}: {exc}") from exc
        self._buf = b""

    def _close_port(self) -> None:
        port, self._port = self._port, None
        if port is not None:
            with contextlib.suppress(Exception):
                port.close()

    def close(self) -> None:
        """Stop streaming, switch the laser off, release the port. Idempotent, never raises."""
        with contextlib.suppress(Exception):
            self.stop()
        self._close_port()

    def __enter__(self) -> HokuyoLidar:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- request / reply -------------------------------------------------------------------
    def _write(self, data: bytes) -> None:
        self.open()
        assert self._port is not None
        try:
            self._port.write(data)
            self._port.flush()
        except (serial.SerialException, OSError) as exc:
            raise HokuyoError(f"hokuyo: writing to {self.url} failed: {exc}") from exc

    def _read_block(self, timeout_s: float, what: str) -> bytes:
        """Bytes up to and including the next LF LF."""
        deadline = time.monotonic() + timeout_s
        while True:
            end = self._buf.find(b"\n\n")
            if end >= 0:
                block, self._buf = self._buf[: end + 2], self._buf[end + 2 :]
                return block
            if time.monotonic() > deadline:
                raise ScipTimeout(
                    f"hokuyo: no complete reply to {what} from {self.url} within {timeout_s:g} s"
                    + (f" (got {self._buf[:60]!r})" if self._buf else "")
                )
            port = self._port
            if port is None:
                raise HokuyoError(f"hokuyo: port {self.url} is closed")
            try:
                chunk = port.read(65536)
            except (serial.SerialException, OSError) as exc:
                raise HokuyoError(f"hokuyo: reading from {self.url} failed: {exc}") from exc
            if chunk:
                self._buf += chunk
            else:
                time.sleep(0.0005)

    def command(self, request: str, ok: tuple[str, ...] = ("00",)) -> Reply:
        """Send ``request`` (without LF) and return its reply; :class:`ScipStatusError` if the
        status is not in ``ok``. Replies to other requests (stray stream data) are skipped."""
        with self._io:
            self._write(request.encode("ascii") + b"\n")
            deadline = time.monotonic() + self.timeout_s
            want = request.encode("ascii")
            while True:
                block = self._read_block(max(0.0, deadline - time.monotonic()), request)
                if block.split(b"\n", 1)[0] != want:
                    continue  # a scan of a stream being stopped, or a stale reply
                rep = scip.parse_reply(block, request, kv=request in ("VV", "PP", "II"))
                if rep.status not in ok:
                    raise ScipStatusError(request, rep.status)
                return rep

    # --- identity --------------------------------------------------------------------------
    def version(self) -> dict[str, str]:
        """VV fields (VEND, PROD, FIRM, PROT, SERI)."""
        self._version = self.command("VV").fields()
        return dict(self._version)

    def parameters(self) -> SensorParameters:
        """PP: range limits, step geometry and mirror speed (cached after the first call)."""
        if self._params is None:
            self._params = SensorParameters.from_fields(self.command("PP").fields())
        return self._params

    def status_fields(self) -> dict[str, str]:
        """II fields (MODL, LASR, SCSP, MESM, SBPS, TIME, STAT)."""
        return self.command("II").fields()

    def mapping(self) -> StepMapping:
        """The step → azimuth mapping in use."""
        p = self.parameters()
        bore = self.settings["boresight_step"]
        return StepMapping(
            ares=p.ares,
            boresight_step=float(p.afrt if bore is None else bore),
            sign=int(self.settings["azimuth_sign"]),
        )

    def _window(self) -> tuple[int, int, int]:
        p = self.parameters()
        start = p.amin if self.settings["start_step"] is None else int(self.settings["start_step"])
        end = p.amax if self.settings["end_step"] is None else int(self.settings["end_step"])
        if not p.amin <= start <= end <= p.amax:
            raise HokuyoError(
                f"hokuyo: settings start_step/end_step {start}..{end} must lie within the "
                f"sensor's AMIN..AMAX {p.amin}..{p.amax}"
            )
        return start, end, max(1, int(self.settings["cluster"]))

    def info(self) -> LidarInfo:
        """Identity (VV) and geometry (PP) as a :class:`LidarInfo`."""
        v = self._version or self.version()
        p = self.parameters()
        start, end, cluster = self._window()
        az = self.mapping().azimuths(start, end, cluster)
        return LidarInfo(
            vendor=v.get("VEND", "Hokuyo"),
            model=p.model or v.get("PROD", ""),
            serial=v.get("SERI", ""),
            fov_rad=float(abs(az[-1] - az[0])) if len(az) > 1 else 0.0,
            points_per_line=len(az),
            line_rate_hz=p.scan_rpm / 60.0,
            range_min_m=p.dmin_mm / 1000.0,
            range_max_m=p.dmax_mm / 1000.0,
            extra={
                "protocol": v.get("PROT", "SCIP 2.0"),
                "firmware": v.get("FIRM", ""),
                "product": v.get("PROD", ""),
                "port": self.url,
                "ares": p.ares,
                "amin": p.amin,
                "amax": p.amax,
                "afrt": p.afrt,
                "scan_rpm": p.scan_rpm,
                "start_step": start,
                "end_step": end,
                "cluster": cluster,
                "azimuth_sign": int(self.settings["azimuth_sign"]),
                "boresight_step": self.mapping().boresight_step,
            },
        )

    # --- laser and clock -------------------------------------------------------------------
    def laser_on(self) -> None:
        """BM; status 01 (laser malfunction) raises, 02 (already on) is fine."""
        try:
            self.command("BM", ok=("00", "02"))
        except ScipStatusError as exc:
            if exc.status == "01":
                raise HokuyoError(
                    "hokuyo: the sensor reports a laser malfunction (BM status 01)"
                ) from exc
            raise

    def laser_off(self) -> None:
        """QT: stop streaming and switch the laser off."""
        self.command("QT")

    def reset(self) -> None:
        """RS: stop, laser off, back to the power-on state (keeps the sensor clock)."""
        self.command("RS")
        self._params = None

    def sync_clock(self, round_trips: int | None = None) -> float:
        """TM0, ``round_trips`` × TM1, TM2; updates :attr:`sync`; returns the best round trip s."""
        n = int(self.settings["sync_round_trips"] if round_trips is None else round_trips)
        self.command("TM0", ok=("00", "02"))
        try:
            for _ in range(max(1, n)):
                t0 = self.clock.now_ns()
                rep = self.command("TM1")
                t1 = self.clock.now_ns()
                if len(rep.lines) != 1 or len(rep.lines[0]) != 4:
                    raise scip.ScipProtocolError(f"TM1 reply carries no time: {rep.lines!r}")
                self.sync.add(t0, t1, scip.decode_value(rep.lines[0]))
        finally:
            self.command("TM2", ok=("00", "03"))
        self.last_round_trip_s = self.sync.commit()
        return self.last_round_trip_s

    def _line_from(self, stamp_ms: int, values: np.ndarray, smooth: bool) -> LidarLine:
        p = self.parameters()
        start, end, cluster = self._window()
        if not self.sync.synced:
            self.sync_clock()
        ms = float(self.sync.unwrap(stamp_ms))
        if smooth and self._time_filter is not None:
            ms = self._time_filter(ms)
        host0 = self.sync.to_host_ns(ms)
        offset_s = float(self.settings["timestamp_offset_s"]) + (start - p.amin) * p.step_period_s
        # a cluster's value is taken at its centre step
        offset_s += (cluster - 1) / 2 * p.step_period_s
        key = (start, end, cluster)
        if key not in self._azimuths:
            self._azimuths = {key: self.mapping().azimuths(start, end, cluster)}
        az = self._azimuths[key]
        if len(values) != len(az):
            raise scip.ScipProtocolError(
                f"hokuyo: scan carries {len(values)} values, expected {len(az)}"
            )
        valid = (values >= p.dmin_mm) & (values <= p.dmax_mm)
        return LidarLine(
            timestamp_ns=host0 + round(offset_s * 1e9),
            azimuth_rad=az.copy(),
            range_m=values.astype(np.float64) / 1000.0,
            valid=valid,
            point_period_ns=p.step_period_s * cluster * 1e9,
        )

    # --- single scans ----------------------------------------------------------------------
    def single_scan(self) -> LidarLine:
        """One scan by GD (or GS), laser switched on first. Status 10 (laser off) raises."""
        start, end, cluster = self._window()
        if not self.sync.synced:
            self.sync_clock()
        self.laser_on()
        name = "GD" if self.settings["encoding"] == "D" else "GS"
        request = f"{name}{start:04d}{end:04d}{_cluster_field(cluster)}"
        try:
            rep = self.command(request)
        except ScipStatusError as exc:
            if exc.status == "10":
                raise HokuyoError(
                    f"hokuyo: {request} answered status 10: the laser is off"
                ) from exc
            raise
        stamp, values = scip.scan_payload(rep, 3 if name == "GD" else 2)
        return self._line_from(stamp, values, smooth=False)

    # --- streaming -------------------------------------------------------------------------
    def start(self) -> None:
        """Sync the clock, switch the laser on and start an endless MD/MS stream."""
        if self._reader is not None:
            return
        self.open()
        self.command("QT")  # whatever the sensor was doing, stop it
        self.sync_clock()
        self.laser_on()
        start, end, cluster = self._window()
        name = "MD" if self.settings["encoding"] == "D" else "MS"
        self._stream_request = f"{name}{start:04d}{end:04d}{_cluster_field(cluster)}000"
        self._time_filter = _ScanTimeFilter(self.parameters().scan_period_s * 1000.0)
        self.command(self._stream_request)
        self._queue = queue.Queue()
        self._streaming.set()
        self._reader = threading.Thread(target=self._read_stream, name="hokuyo-reader",
                                         daemon=True)
        self._reader.start()

    def _read_stream(self) -> None:
        chars = 3 if self._stream_request.startswith("MD") else 2
        head = self._stream_request[:13].encode("ascii")
        while self._streaming.is_set():
            try:
                with self._io:
                    block = self._read_block(0.1, self._stream_request)
            except ScipTimeout:
                continue
            except HokuyoError as exc:
                if self._streaming.is_set():
                    self._queue.put(exc)
                return
            if not block.startswith(head):
                continue
            try:
                rep = scip.parse_reply(block, self._stream_request)
                if rep.status == "00":
                    continue
                if rep.status != "99":
                    raise ScipStatusError(self._stream_request, rep.status)
                stamp, values = scip.scan_payload(rep, chars)
                self._queue.put(self._line_from(stamp, values, smooth=True))
            except scip.ScipChecksumError as exc:
                self.bad_sums += 1
                if self.bad_sums > int(self.settings["max_bad_sums"]):
                    self._queue.put(exc)
                else:
                    log.warning("%s (scan dropped)", exc)
            except HokuyoError as exc:
                self._queue.put(exc)

    def lines(self) -> Iterator[LidarLine]:
        """Streamed lines until :meth:`stop`. After ``timeout_s`` of silence the driver reconnects
        (up to ``reconnect_attempts`` times) and resumes; then :class:`ScipTimeout`."""
        attempts = 0
        while self._streaming.is_set():
            try:
                item = self._queue.get(timeout=self.timeout_s)
            except queue.Empty:
                if not self._streaming.is_set():
                    return
                if attempts >= int(self.settings["reconnect_attempts"]):
                    self._stop_reader()
                    raise ScipTimeout(
                        f"hokuyo: no scan from {self.url} for {self.timeout_s:g} s "
                        f"(after {attempts} reconnect attempt(s))"
                    ) from None
                attempts += 1
                self._reconnect()
                continue
            if isinstance(item, BaseException):
                self._stop_reader()
                raise item
            attempts = 0
            yield item

    def _reconnect(self) -> None:
        log.warning("hokuyo: %s went silent; reconnecting", self.url)
        self.reconnects += 1
        self._stop_reader()
        self._close_port()
        with contextlib.suppress(HokuyoError):
            self.start()
        if not self._streaming.is_set():
            self._streaming.set()  # keep lines() waiting; the next timeout counts an attempt

    def _stop_reader(self) -> None:
        self._streaming.clear()
        reader, self._reader = self._reader, None
        if reader is not None and reader is not threading.current_thread():
            reader.join(timeout=2)

    def stop(self) -> None:
        """Stop the stream (QT, which also switches the laser off). Safe when not started."""
        was = self._streaming.is_set() or self._reader is not None
        self._stop_reader()
        if was and self._port is not None:
            with contextlib.suppress(HokuyoError):
                self.command("QT")
