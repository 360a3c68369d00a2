"""The example plugin's drivers: a bench turntable, its encoder and a line scanner facing a wall.

A template for a driver plugin. Each class implements one protocol of :mod:`calstation.drivers`
(no base class needed) and is built by a factory ``factory(settings, context)``. Where a real
driver talks to its device (a serial port, a socket, a CAN bus), these compute what an ideal
device would answer from one shared motion model, so the plugin runs anywhere; replace the model
calls with device I/O and keep the rest: the host-clock timestamps, the idempotent ``close``, the
turntable that is stopped on any exit.

Settings (recipe ``station.<kind>.settings``): turntable ``acceleration_rpm_s`` (default 120);
encoder ``counts_per_revolution`` (default 4096); lidar ``wall_distance_m`` (1.0),
``points_per_line`` (360), ``line_rate_hz`` (50), ``fov_deg`` (72), ``range_noise_m`` (0.001),
``serial`` ("EX-0001").
"""

from __future__ import annotations

import math
import threading
from collections.abc import Iterator, Mapping

import numpy as np

from calstation.clock import Clock
from calstation.drivers import (
    DriverContext,
    EncoderSample,
    LidarInfo,
    LidarLine,
    TurntableState,
    TurntableStatus,
)
from calstation.errors import DriverError

SHARED_KEY = "calstation-example"


def _number(settings: Mapping[str, object], key: str, default: float, kind: str) -> float:
    value = settings.get(key, default)
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise DriverError(f"example {kind} driver: setting {key!r} must be a number, got {value!r}")
    return float(value)


class Motion:
    """The platter's motion: speed ramps toward the commanded rpm at ``acceleration_rpm_s``.

    Angle (rad) and speed (rpm) are exact functions of time on ``clock``; the turntable commands
    it, the encoder reads it. Thread-safe.
    """

    def __init__(self, clock: Clock, acceleration_rpm_s: float = 120.0) -> None:
        self.clock = clock
        self.acceleration = acceleration_rpm_s
        self._lock = threading.Lock()
        self._t0 = clock.now_ns()
        self._angle0 = 0.0
        self._speed0 = 0.0
        self._target = 0.0

    def _state(self, t_ns: int) -> tuple[float, float]:
        dt = max(0.0, (t_ns - self._t0) * 1e-9)
        dv = self._target - self._speed0
        ramp = abs(dv) / self.acceleration if self.acceleration > 0 else 0.0
        if dt >= ramp:
            turns = (self._speed0 + self._target) / 2 * ramp + self._target * (dt - ramp)
            speed = self._target
        else:
            speed = self._speed0 + math.copysign(self.acceleration, dv) * dt
            turns = (self._speed0 + speed) / 2 * dt
        return self._angle0 + 2 * math.pi * turns / 60.0, speed

    def command(self, rpm: float, hard: bool = False) -> float:
        """Set the target speed (``hard``: at once, no ramp); returns the ramp time in seconds."""
        with self._lock:
            now = self.clock.now_ns()
            self._angle0, self._speed0 = self._state(now)
            self._t0, self._target = now, rpm
            if hard:
                self._speed0 = rpm
            return abs(rpm - self._speed0) / self.acceleration if self.acceleration > 0 else 0.0

    def at(self, t_ns: int) -> tuple[float, float]:
        """(angle rad, speed rpm) at ``t_ns``."""
        with self._lock:
            return self._state(t_ns)


def _motion(context: DriverContext, settings: Mapping[str, object]) -> Motion:
    shared = context.shared.setdefault(SHARED_KEY, {})
    if "motion" not in shared:
        accel = _number(settings, "acceleration_rpm_s", 120.0, "turntable")
        shared["motion"] = Motion(context.clock, accel)
    motion: Motion = shared["motion"]
    return motion


class ExampleTurntable:
    """A turntable drive (the :class:`calstation.drivers.Turntable` protocol)."""

    def __init__(self, motion: Motion) -> None:
        self.motion = motion
        self.clock = motion.clock
        self._state = TurntableState.DISABLED
        self._closed = False

    def enable(self) -> None:
        """Power the drive."""
        self._check_open()
        self._state = TurntableState.ENABLED

    def disable(self) -> None:
        """Stop, then remove power."""
        self.stop()
        self._state = TurntableState.DISABLED

    def spin(self, rpm: float) -> None:
        """Turn at ``rpm``; returns at once."""
        self._check_open()
        if self._state not in (TurntableState.ENABLED, TurntableState.MOVING):
            raise DriverError(f"example turntable: cannot spin while {self._state.value}")
        self.motion.command(float(rpm))
        self._state = TurntableState.MOVING if rpm else TurntableState.ENABLED

    def move_to(self, angle_rad: float) -> None:
        """Turn the short way to ``angle_rad`` at 5 rpm and return when there."""
        angle, _ = self.motion.at(self.clock.now_ns())
        delta = (angle_rad - angle + math.pi) % (2 * math.pi) - math.pi
        if abs(delta) < 1e-6:
            return
        rpm = math.copysign(5.0, delta)
        self.spin(rpm)
        self.clock.sleep(abs(delta) / (2 * math.pi * 5.0 / 60.0))
        self.motion.command(0.0, hard=True)
        self._state = TurntableState.ENABLED

    def stop(self) -> None:
        """Ramp down and return when standing."""
        if self._state == TurntableState.MOVING:
            self.clock.sleep(self.motion.command(0.0))
            self._state = TurntableState.ENABLED

    def emergency_stop(self) -> None:
        """Stop at once. Never raises."""
        self.motion.command(0.0, hard=True)
        if self._state != TurntableState.DISABLED:
            self._state = TurntableState.EMERGENCY_STOP

    def status(self) -> TurntableStatus:
        """State, speed and angle now."""
        now = self.clock.now_ns()
        angle, speed = self.motion.at(now)
        return TurntableStatus(now, self._state, speed, angle % (2 * math.pi))

    def close(self) -> None:
        """Stop the motor and let go. Idempotent."""
        if not self._closed:
            self.emergency_stop()
            self._closed = True

    def _check_open(self) -> None:
        if self._closed:
            raise DriverError("example turntable: used after close()")


class ExampleEncoder:
    """A quadrature encoder on the platter axis (the :class:`calstation.drivers.Encoder`
    protocol), sampled at 1 kHz."""

    SAMPLE_PERIOD_NS = 1_000_000

    def __init__(self, motion: Motion, counts_per_revolution: int) -> None:
        if counts_per_revolution <= 0:
            raise DriverError(f"example encoder: counts_per_revolution must be positive, got "
                              f"{counts_per_revolution}")
        self.motion = motion
        self.clock = motion.clock
        self._cpr = int(counts_per_revolution)
        self._last_ns = self.clock.now_ns()

    @property
    def counts_per_revolution(self) -> int:
        """Counts per platter revolution."""
        return self._cpr

    def _sample(self, t_ns: int) -> EncoderSample:
        angle, _ = self.motion.at(t_ns)
        return EncoderSample(int(t_ns), math.floor(angle / (2 * math.pi) * self._cpr))

    def read(self) -> EncoderSample:
        """The count now."""
        return self._sample(self.clock.now_ns())

    def samples(self) -> list[EncoderSample]:
        """Every 1 ms sample since the previous call, oldest first."""
        now = self.clock.now_ns()
        times = range(self._last_ns + self.SAMPLE_PERIOD_NS, now + 1, self.SAMPLE_PERIOD_NS)
        out = [self._sample(t) for t in times]
        if out:
            self._last_ns = out[-1].timestamp_ns
        return out

    def close(self) -> None:
        """Nothing to release. Idempotent."""


class ExampleLidar:
    """A line scanner facing a flat wall (the :class:`calstation.drivers.Lidar` protocol)."""

    def __init__(self, clock: Clock, settings: Mapping[str, object]) -> None:
        self.clock = clock
        self.wall = _number(settings, "wall_distance_m", 1.0, "lidar")
        self.points = int(_number(settings, "points_per_line", 360, "lidar"))
        self.rate = _number(settings, "line_rate_hz", 50.0, "lidar")
        self.fov = math.radians(_number(settings, "fov_deg", 72.0, "lidar"))
        self.noise = _number(settings, "range_noise_m", 0.001, "lidar")
        self.serial = str(settings.get("serial", "EX-0001"))
        if self.points <= 0 or self.rate <= 0 or not 0 < self.fov < math.pi:
            raise DriverError("example lidar: points_per_line and line_rate_hz must be positive "
                              "and fov_deg within (0, 180)")
        self._rng = np.random.default_rng(0)
        self._running = threading.Event()
        self._closed = False

    def info(self) -> LidarInfo:
        """Identity and geometry."""
        return LidarInfo("calstation-example", "wall-scanner", self.serial, self.fov,
                         self.points, self.rate, 0.05, 10.0)

    def start(self) -> None:
        """Start streaming."""
        if self._closed:
            raise DriverError("example lidar: used after close()")
        self._running.set()

    def stop(self) -> None:
        """Stop streaming. Safe when not started."""
        self._running.clear()

    def lines(self) -> Iterator[LidarLine]:
        """One line every 1/line_rate_hz seconds until :meth:`stop`."""
        azimuth = np.linspace(-self.fov / 2, self.fov / 2, self.points)
        period_ns = int(1e9 / self.rate)
        point_ns = period_ns * 0.9 / self.points
        next_ns = self.clock.now_ns()
        while self._running.is_set():
            wait = (next_ns - self.clock.now_ns()) * 1e-9
            if wait > 0:
                self.clock.sleep(wait)
            ranges = self.wall / np.cos(azimuth) + self._rng.normal(0.0, self.noise, self.points)
            valid = (ranges > 0.05) & (ranges < 10.0)
            yield LidarLine(next_ns, azimuth, ranges, valid, point_period_ns=point_ns)
            next_ns += period_ns

    def close(self) -> None:
        """Stop. Idempotent."""
        self.stop()
        self._closed = True


def turntable_factory(settings: Mapping[str, object], context: DriverContext) -> ExampleTurntable:
    """``station.turntable.driver: example``."""
    return ExampleTurntable(_motion(context, settings))


def encoder_factory(settings: Mapping[str, object], context: DriverContext) -> ExampleEncoder:
    """``station.encoder.driver: example``."""
    cpr = int(_number(settings, "counts_per_revolution", 4096, "encoder"))
    return ExampleEncoder(_motion(context, {}), cpr)


def lidar_factory(settings: Mapping[str, object], context: DriverContext) -> ExampleLidar:
    """``station.lidar.driver: example``."""
    return ExampleLidar(context.clock, settings)
