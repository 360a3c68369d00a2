"""Conformance checks a driver plugin runs against its own Lidar, Turntable and Encoder.

Each check takes a *factory*: a callable with no arguments that returns a fresh, ready driver
(typically ``lambda: my_factory(settings, DriverContext(clock=HostClock()))`` around an emulator
of the device). It exercises the driver through the protocol of :mod:`calstation.drivers` the way
the station does, and raises :class:`ConformanceError` (an ``AssertionError``, so pytest shows it
as a failed test) naming the driver and the broken rule. On success it returns what it measured.

Use the functions directly, or subclass :class:`DriverConformance` in a test module::

    from calstation.testing.conformance import DriverConformance

    class TestMyDrivers(DriverConformance):
        def make_lidar(self):
            return my_lidar_factory({"port": emulator.url}, context())

Drivers that keep their own time (a simulator) expose a ``clock`` attribute (see
:class:`calstation.drivers.DriverContext`); the checks wait on it instead of the host clock.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TypeVar

import numpy as np

from calstation.clock import Clock, HostClock
from calstation.drivers import (
    Encoder,
    EncoderSample,
    Lidar,
    LidarInfo,
    LidarLine,
    Turntable,
    TurntableState,
    TurntableStatus,
)

_D = TypeVar("_D", Lidar, Turntable, Encoder)
DriverFactory = Callable[[], _D]
"""A callable returning a fresh, ready driver (of the kind checked: whether it really is one is
the check's first rule)."""


class ConformanceError(AssertionError):
    """A driver broke a rule of its protocol."""


@dataclass
class ConformanceReport:
    """What a check measured: the driver's type and the rules it passed, in order."""

    driver: str
    passed: list[str] = field(default_factory=list)
    measured: dict[str, object] = field(default_factory=dict)


def _require(ok: bool, report: ConformanceReport, rule: str, detail: str = "") -> None:
    if not ok:
        raise ConformanceError(f"{report.driver}: {rule}" + (f" ({detail})" if detail else ""))
    report.passed.append(rule)


def _clock_of(driver: object) -> Clock:
    clock = getattr(driver, "clock", None)
    return clock if clock is not None else HostClock()


def _closes_twice(driver: Lidar | Turntable | Encoder, report: ConformanceReport) -> None:
    try:
        driver.close()
        driver.close()
    except Exception as exc:
        raise ConformanceError(f"{report.driver}: close() must be idempotent: {exc!r}") from exc
    report.passed.append("close() is idempotent")


# --- lidar ---------------------------------------------------------------------------------------
def check_lidar(
    make: DriverFactory[Lidar], *, lines: int = 5, timeout_s: float = 10.0
) -> ConformanceReport:
    """Check a :class:`~calstation.drivers.Lidar`: identity, ``lines()`` data, start/stop/close.

    Rules: it satisfies the protocol; ``info()`` is a :class:`LidarInfo` with a positive field of
    view, points per line and line rate and ``range_min_m < range_max_m``; ``stop()`` before
    ``start()`` is safe; after ``start()``, ``lines`` lines come within ``timeout_s`` (host
    seconds), each a :class:`LidarLine` with finite azimuths inside the field of view (±2 %),
    finite ranges within the valid range where marked valid, non-decreasing point times, line
    timestamps strictly increasing, and at least one valid point overall; ``close()`` twice is
    safe.
    """
    driver = make()
    report = ConformanceReport(type(driver).__name__)
    try:
        _require(isinstance(driver, Lidar), report, "implements the Lidar protocol",
                 "info, start, stop, lines, close")
        info = driver.info()
        _check_info(info, report)
        driver.stop()
        report.passed.append("stop() before start() is safe")
        driver.start()
        try:
            got = _take_lines(driver, lines, timeout_s, report)
        finally:
            driver.stop()
        _check_lines(got, info, report)
    finally:
        _closes_twice(driver, report)
    return report


def _check_info(info: LidarInfo, report: ConformanceReport) -> None:
    _require(isinstance(info, LidarInfo), report, "info() returns a LidarInfo",
             type(info).__name__)
    _require(math.isfinite(info.fov_rad) and 0 < info.fov_rad <= 2 * math.pi, report,
             "info().fov_rad in (0, 2π]", f"{info.fov_rad}")
    _require(info.points_per_line > 0, report, "info().points_per_line > 0",
             f"{info.points_per_line}")
    _require(math.isfinite(info.line_rate_hz) and info.line_rate_hz > 0, report,
             "info().line_rate_hz > 0", f"{info.line_rate_hz}")
    _require(0 <= info.range_min_m < info.range_max_m, report,
             "0 ≤ info().range_min_m < range_max_m", f"{info.range_min_m}, {info.range_max_m}")
    report.measured["serial"] = info.serial


def _take_lines(
    driver: Lidar, n: int, timeout_s: float, report: ConformanceReport
) -> list[LidarLine]:
    got: list[LidarLine] = []
    deadline = time.monotonic() + timeout_s
    for line in driver.lines():
        got.append(line)
        if len(got) >= n:
            break
        if time.monotonic() > deadline:
            break
    _require(len(got) >= n, report, f"lines() yields {n} lines after start()",
             f"got {len(got)} within {timeout_s:g} s")
    return got


def _check_lines(got: list[LidarLine], info: LidarInfo, report: ConformanceReport) -> None:
    half = 0.5 * info.fov_rad * 1.02
    previous: int | None = None
    valid_total = 0
    for i, line in enumerate(got):
        _require(isinstance(line, LidarLine), report, "lines() yields LidarLine objects",
                 f"line {i} is {type(line).__name__}")
        az = np.asarray(line.azimuth_rad, dtype=float)
        rng = np.asarray(line.range_m, dtype=float)
        valid = np.asarray(line.valid, dtype=bool)
        _require(len(line) > 0, report, "every line has points", f"line {i} is empty")
        _require(bool(np.isfinite(az).all()) and bool((np.abs(az) <= half).all()), report,
                 "azimuths are finite and inside the field of view",
                 f"line {i}: {az.min():.4f}..{az.max():.4f} rad, fov {info.fov_rad:.4f}")
        good = rng[valid]
        _require(bool(np.isfinite(good).all()) and bool(
            ((good >= info.range_min_m * 0.999) & (good <= info.range_max_m * 1.001)).all()),
            report, "valid ranges are finite and within [range_min_m, range_max_m]",
            f"line {i}")
        times = line.point_times_ns()
        _require(bool((np.diff(times) >= 0).all()), report, "point times never go backwards",
                 f"line {i}")
        _require(isinstance(line.timestamp_ns, int | np.integer), report,
                 "timestamps are integer nanoseconds", f"line {i}: {line.timestamp_ns!r}")
        if previous is not None:
            _require(int(line.timestamp_ns) > previous, report,
                     "line timestamps strictly increase",
                     f"line {i}: {line.timestamp_ns} after {previous}")
        previous = int(line.timestamp_ns)
        valid_total += int(valid.sum())
    _require(valid_total > 0, report, "the lines hold valid returns", "every point invalid")
    report.measured["lines"] = len(got)
    report.measured["valid_fraction"] = valid_total / max(1, sum(len(x) for x in got))


# --- turntable -----------------------------------------------------------------------------------
def check_turntable(
    make: DriverFactory[Turntable], *, rpm: float = 10.0, spin_s: float = 3.0
) -> ConformanceReport:
    """Check a :class:`~calstation.drivers.Turntable`: enable, spin, status, stop, e-stop, close.

    Rules: it satisfies the protocol; ``status()`` is a :class:`TurntableStatus`;
    ``emergency_stop()`` on a standing drive does not raise; after ``enable()`` and ``spin(rpm)``
    (which returns within 1 host second) and ``spin_s`` seconds on the driver's clock the state is
    ``moving`` with the speed within 20 % of ``rpm`` and the sign of ``rpm``, and no faults;
    ``stop()`` brings the speed below 5 % of ``rpm``; ``emergency_stop()`` while spinning leaves it
    stopped or in emergency stop without raising; ``close()`` twice is safe.
    """
    driver = make()
    report = ConformanceReport(type(driver).__name__)
    clock = _clock_of(driver)
    try:
        _require(isinstance(driver, Turntable), report, "implements the Turntable protocol",
                 "enable, disable, spin, move_to, stop, emergency_stop, status, close")
        status = driver.status()
        _require(isinstance(status, TurntableStatus), report, "status() returns a TurntableStatus",
                 type(status).__name__)
        driver.emergency_stop()
        report.passed.append("emergency_stop() on a standing drive does not raise")
        driver.enable()
        t0 = time.monotonic()
        driver.spin(rpm)
        _require(time.monotonic() - t0 < 1.0, report, "spin() returns at once",
                 f"took {time.monotonic() - t0:.2f} s")
        clock.sleep(spin_s)
        moving = driver.status()
        report.measured["speed_rpm"] = moving.speed_rpm
        _require(moving.state == TurntableState.MOVING, report, "spinning reports state moving",
                 f"state {moving.state}")
        _require(not moving.faults, report, "spinning reports no faults", ", ".join(moving.faults))
        _require(math.copysign(1.0, moving.speed_rpm) == math.copysign(1.0, rpm)
                 and abs(moving.speed_rpm - rpm) <= 0.2 * abs(rpm), report,
                 "the speed reaches the commanded rpm (±20 %)",
                 f"{moving.speed_rpm:.2f} rpm for {rpm:g}")
        driver.stop()
        stopped = driver.status()
        _require(abs(stopped.speed_rpm) <= 0.05 * abs(rpm), report, "stop() stands the platter",
                 f"{stopped.speed_rpm:.2f} rpm after stop()")
        driver.spin(rpm)
        clock.sleep(0.5)
        driver.emergency_stop()
        clock.sleep(0.5)
        after = driver.status()
        _require(after.state in (TurntableState.EMERGENCY_STOP, TurntableState.DISABLED,
                                 TurntableState.ENABLED, TurntableState.FAULT)
                 and abs(after.speed_rpm) <= 0.05 * abs(rpm), report,
                 "emergency_stop() stops a spinning platter",
                 f"state {after.state}, {after.speed_rpm:.2f} rpm")
    finally:
        try:
            driver.stop()
        except Exception:  # the drive may refuse stop() after an emergency stop: that is allowed
            driver.emergency_stop()
        _closes_twice(driver, report)
    return report


# --- encoder -------------------------------------------------------------------------------------
def check_encoder(
    make: DriverFactory[Encoder], *, turn: Callable[[Encoder], object] | None = None,
    reads: int = 20,
) -> ConformanceReport:
    """Check an :class:`~calstation.drivers.Encoder`: counts per revolution, read, samples, close.

    Rules: it satisfies the protocol; ``counts_per_revolution`` is a positive integer;
    ``read()`` gives an :class:`EncoderSample` with integer time and count, times never going
    backwards over ``reads`` reads; ``samples()`` is a list of samples, oldest first; when
    ``turn`` is given (``turn(encoder)`` makes the platter move, e.g. by spinning the matching
    turntable emulator for a while) the count changes across it; ``close()`` twice is safe.
    """
    driver = make()
    report = ConformanceReport(type(driver).__name__)
    try:
        _require(isinstance(driver, Encoder), report, "implements the Encoder protocol",
                 "counts_per_revolution, read, samples, close")
        cpr = driver.counts_per_revolution
        _require(isinstance(cpr, int | np.integer) and int(cpr) > 0, report,
                 "counts_per_revolution is a positive integer", repr(cpr))
        previous: int | None = None
        first: EncoderSample | None = None
        for i in range(reads):
            s = driver.read()
            _require(isinstance(s, EncoderSample), report, "read() returns an EncoderSample",
                     type(s).__name__)
            _require(isinstance(s.timestamp_ns, int | np.integer)
                     and isinstance(s.count, int | np.integer), report,
                     "samples carry integer nanoseconds and counts",
                     f"read {i}: {s.timestamp_ns!r}, {s.count!r}")
            if previous is not None:
                _require(int(s.timestamp_ns) >= previous, report, "read() times never go back",
                         f"read {i}: {s.timestamp_ns} after {previous}")
            previous = int(s.timestamp_ns)
            first = first or s
        batch = driver.samples()
        _require(isinstance(batch, list) and all(isinstance(x, EncoderSample) for x in batch),
                 report, "samples() returns a list of EncoderSample")
        times = [int(x.timestamp_ns) for x in batch]
        _require(times == sorted(times), report, "samples() are oldest first")
        if turn is not None and first is not None:
            turn(driver)
            last = driver.read()
            report.measured["counts_turned"] = int(last.count) - int(first.count)
            _require(int(last.count) != int(first.count), report,
                     "the count changes when the platter turns",
                     f"count stayed {first.count}")
    finally:
        _closes_twice(driver, report)
    return report


# --- pytest base class ---------------------------------------------------------------------------
class DriverConformance:
    """Subclass it in a test module (class name starting with ``Test``) and implement the
    ``make_*`` methods for the drivers the plugin provides; a ``make_*`` left returning None
    skips that check. ``turn_encoder`` may move the platter for the encoder check."""

    turntable_rpm = 10.0

    def make_lidar(self) -> Lidar | None:
        """A fresh lidar driver (None: the plugin has none)."""
        return None

    def make_turntable(self) -> Turntable | None:
        """A fresh turntable driver (None: the plugin has none)."""
        return None

    def make_encoder(self) -> Encoder | None:
        """A fresh encoder driver (None: the plugin has none)."""
        return None

    def turn_encoder(self, encoder: Encoder) -> None:
        """Make the platter under ``encoder`` move (default: nothing, the check is skipped)."""

    def _factory(self, make: Callable[[], _D | None], name: str) -> DriverFactory[_D]:
        import pytest

        probe = make()
        if probe is None:
            pytest.skip(f"the plugin provides no {name} driver")
        made = [probe]

        def factory() -> _D:
            driver = made.pop() if made else make()
            if driver is None:
                raise ConformanceError(f"make_{name}() gave a driver once, then None")
            return driver

        return factory

    def test_lidar_conforms(self) -> None:
        """The lidar follows the Lidar protocol."""
        check_lidar(self._factory(self.make_lidar, "lidar"))

    def test_turntable_conforms(self) -> None:
        """The turntable follows the Turntable protocol."""
        check_turntable(self._factory(self.make_turntable, "turntable"), rpm=self.turntable_rpm)

    def test_encoder_conforms(self) -> None:
        """The encoder follows the Encoder protocol."""
        turn = self.turn_encoder if type(self).turn_encoder is not DriverConformance.turn_encoder \
            else None
        check_encoder(self._factory(self.make_encoder, "encoder"), turn=turn)
