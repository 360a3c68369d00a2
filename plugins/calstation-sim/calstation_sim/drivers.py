"""The ``sim`` lidar, turntable and encoder drivers: calstation's driver protocols over one
:class:`~calstation_sim.station.SimulatedStation`.

All three run on the station's clock and expose it as ``.clock``. With the default
:class:`~calstation.clock.SimClock` the lidar advances the clock as it produces lines (a run takes
as long as the computation); with a real-time clock it waits for each line's end instead.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np

from calstation.clock import Clock, HostClock, SimClock
from calstation.drivers import (
    DriverContext,
    EncoderSample,
    LidarInfo,
    LidarLine,
    TurntableState,
    TurntableStatus,
)
from calstation.errors import DriverError

from .settings import SimSettings
from .station import SimulatedStation, shared_station

BATCH_LINES = 100
"""Lines ray-cast per batch (yielded one by one)."""

MOVE_RPM = 10.0
"""Cruise speed of :meth:`SimTurntable.move_to`."""

ENCODER_BUFFER_S = 60.0
"""A background encoder stream keeps at most this much history between two ``samples()``."""

EMERGENCY_DECELERATION_FACTOR = 10.0

REAL_TIME_BUFFER_S = 30.0
"""On the host's clock, the lidar keeps the lines it has not handed over for this long (a network
lidar's, the host's socket buffer): a consumer that falls behind, on a loaded host, gets every
line late and in order, not a scan with holes; older lines are dropped."""


def _wait_until(clock: Clock, t_ns: int) -> None:
    if isinstance(clock, SimClock):
        clock.advance_to(t_ns)
        return
    remaining = (t_ns - clock.now_ns()) * 1e-9
    if remaining > 0:
        clock.sleep(remaining)


class SimLidar:
    """The simulated line scanner (satisfies :class:`calstation.drivers.Lidar`).

    Lines lie on a fixed grid from :meth:`start`: line k starts at ``t_start + k·period``. On a
    SimClock, when the consumer lets simulated time pass (``clock.sleep``), lines that started in
    the past are skipped, as a device without a buffer would drop them; on a real-time clock the
    lines are produced in order, each once real time has reached its end, and one that could
    not be computed in time (a loaded host) is handed over late rather than skipped, unless it
    is older than :data:`REAL_TIME_BUFFER_S`.
    """

    def __init__(self, station: SimulatedStation) -> None:
        self.station = station
        self.clock = station.clock
        self._running = False
        self._t_start = 0
        self._next = 0

    def info(self) -> LidarInfo:
        """The simulated device's identity and geometry."""
        return self.station.lidar_info

    def start(self) -> None:
        """Start streaming lines from the clock's current time."""
        self._running = True
        self._t_start = self.clock.now_ns()
        self._next = 0

    def stop(self) -> None:
        """Stop streaming; a running :meth:`lines` iterator ends."""
        self._running = False

    def _line_time(self, k: int) -> int:
        return self._t_start + round(k * self.station.line_period_ns)

    def lines(self) -> Iterator[LidarLine]:
        """Lines in time order until :meth:`stop`; each advances the clock to its end."""
        if not self._running:
            raise DriverError("sim lidar: lines() called before start()")
        period = self.station.line_period_ns
        simulated = isinstance(self.clock, SimClock)
        kept_ns = 0.0 if simulated else REAL_TIME_BUFFER_S * 1e9
        while self._running:
            behind = (self.clock.now_ns() - kept_ns - self._t_start) / period
            k0 = max(self._next, math.ceil(behind - 1e-9))
            revision = self.station.revision
            times = np.array([self._line_time(k) for k in range(k0, k0 + BATCH_LINES)])
            batch = self.station.scan_lines(times)
            for j, line in enumerate(batch):
                if not self._running:
                    return
                if self.station.revision != revision:
                    break  # the scene or the motion changed: recompute from here
                if simulated and line.timestamp_ns < self.clock.now_ns():
                    continue  # the consumer let simulated time pass: this line is gone
                _wait_until(self.clock, self._line_time(k0 + j + 1))
                self._next = k0 + j + 1
                yield line

    def close(self) -> None:
        """Stop streaming. Idempotent."""
        self._running = False


class SimTurntable:
    """The simulated turntable drive (satisfies :class:`calstation.drivers.Turntable`)."""

    def __init__(self, station: SimulatedStation) -> None:
        self.station = station
        self.clock = station.clock
        self._enabled = False
        self._estop = False

    def enable(self) -> None:
        """Power the drive (clears an emergency stop)."""
        self._enabled = True
        self._estop = False

    def disable(self) -> None:
        """Stop, then remove power."""
        if self._enabled:
            self.stop()
        self._enabled = False

    def _check_enabled(self, what: str) -> None:
        if self._estop:
            raise DriverError(
                f"sim turntable: cannot {what} after an emergency stop; enable() first"
            )
        if not self._enabled:
            raise DriverError(f"sim turntable: cannot {what} while disabled; enable() first")

    def spin(self, rpm: float) -> None:
        """Ramp to ``rpm`` (signed) and keep turning. Returns at once."""
        if not math.isfinite(rpm):
            raise DriverError(f"sim turntable: speed must be finite, got {rpm}")
        self._check_enabled("spin")
        self.station.set_speed(rpm, self.clock.now_ns())

    def move_to(self, angle_rad: float) -> None:
        """Turn the shortest way to ``angle_rad`` (mod 2π) with a trapezoidal profile; returns
        when there (the speed ripple leaves a small residual)."""
        self._check_enabled("move")
        self.stop()
        now = self.clock.now_ns()
        phi = self.station.platter_angle(now)
        delta = (angle_rad - phi + math.pi) % (2 * math.pi) - math.pi
        if abs(delta) < 1e-9:
            return
        acc = self.station.motion.acceleration
        w_max = MOVE_RPM * 2 * math.pi / 60.0
        # accelerate, cruise, decelerate (triangular when the move is short)
        w = min(w_max, math.sqrt(abs(delta) * acc))
        t_ramp = w / acc
        t_cruise = (abs(delta) - w * t_ramp) / w
        rpm = math.copysign(w * 60.0 / (2 * math.pi), delta)
        self.station.set_speed(rpm, now)
        t_brake = now + round((t_ramp + t_cruise) * 1e9)
        _wait_until(self.clock, t_brake)
        end = self.station.set_speed(0.0, t_brake)
        _wait_until(self.clock, end)

    def stop(self) -> None:
        """Ramp down to standstill; returns when stopped."""
        end = self.station.set_speed(0.0, self.clock.now_ns())
        _wait_until(self.clock, end)

    def emergency_stop(self) -> None:
        """Stop at ten times the normal deceleration. Never raises."""
        try:
            acc = self.station.config.turntable.acceleration_rpm_s * EMERGENCY_DECELERATION_FACTOR
            end = self.station.set_speed(0.0, self.clock.now_ns(), acceleration_rpm_s=acc)
            _wait_until(self.clock, end)
        except Exception:  # an emergency stop must never raise
            pass
        self._estop = True

    def status(self) -> TurntableStatus:
        """State, actual speed (rpm, ripple included) and true angle (rad) now."""
        now = self.clock.now_ns()
        speed = self.station.platter_speed_rpm(now)
        if self._estop:
            state = TurntableState.EMERGENCY_STOP
        elif not self._enabled:
            state = TurntableState.DISABLED
        elif speed != 0.0 or self.station.motion.commanded_speed() != 0.0:
            state = TurntableState.MOVING
        else:
            state = TurntableState.ENABLED
        return TurntableStatus(
            timestamp_ns=now,
            state=state,
            speed_rpm=speed,
            position_rad=self.station.platter_angle(now),
        )

    def close(self) -> None:
        """Stop if moving. Idempotent."""
        if self.station.motion.commanded_speed() != 0.0:
            self.stop()
        self._enabled = False


class SimEncoder:
    """The simulated quadrature encoder (satisfies :class:`calstation.drivers.Encoder`).

    A background stream of samples every ``1/sample_rate_hz`` from the station's time origin;
    sample k is taken at true time ``t_k`` and stamped ``t_k + latency``.
    """

    def __init__(self, station: SimulatedStation) -> None:
        self.station = station
        self.clock = station.clock
        self._last_ns: int | None = None  # timestamp of the latest sample handed out

    @property
    def counts_per_revolution(self) -> int:
        """4·ppr."""
        return self.station.counts_per_revolution

    def read(self) -> EncoderSample:
        """One reading now (stamped now + latency)."""
        t = self.clock.now_ns() + self.station.encoder_latency_ns
        self._last_ns = t if self._last_ns is None else max(self._last_ns, t)
        return EncoderSample(timestamp_ns=t, count=self.station.encoder_count(t))

    def samples(self) -> list[EncoderSample]:
        """The stream's samples taken since the previous call (at most the last minute)."""
        st = self.station
        period = st.encoder_sample_period_ns
        k_now = math.floor((self.clock.now_ns() - st.time_origin_ns) / period + 1e-9)
        k_first = k_now - math.floor(ENCODER_BUFFER_S * 1e9 / period)
        if self._last_ns is not None:
            after = (self._last_ns - st.encoder_latency_ns - st.time_origin_ns) / period
            k_first = max(k_first, math.floor(after + 1e-9) + 1)
        k_first = max(k_first, 0)
        if k_now < k_first:
            return []
        ks = np.arange(k_first, k_now + 1)
        stamps = st.time_origin_ns + np.round(ks * period).astype(np.int64) + st.encoder_latency_ns
        stamps = stamps[stamps > (self._last_ns if self._last_ns is not None else -1)]
        if len(stamps) == 0:
            return []
        counts = st.encoder_counts(stamps)
        self._last_ns = int(stamps[-1])
        return [
            EncoderSample(timestamp_ns=int(t), count=int(c))
            for t, c in zip(stamps.tolist(), counts.tolist(), strict=True)
        ]

    def close(self) -> None:
        """Nothing to release."""


# --- factories --------------------------------------------------------------------------------
_SETTINGS = {"seed", "range_m", "pitch_deg", "real_time"}


def station_from_context(
    settings: Mapping[str, Any], context: DriverContext  # Any: the recipe's, checked by SimSettings
) -> SimulatedStation:
    """The run's :class:`SimulatedStation` from ``context.shared["sim"]``, created on first use
    from ``context.recipe`` and the driver ``settings`` (optional ``seed``, ``range_m``,
    ``pitch_deg``, ``real_time``). The station runs on ``context.clock`` if that is a SimClock,
    else on a SimClock of its own; with ``real_time``, on the host's clock (``context.clock``
    when that is not a SimClock).
    """
    unknown = set(settings) - _SETTINGS
    if unknown:
        raise DriverError(
            f"sim driver: unknown setting(s) {', '.join(sorted(unknown))}; "
            f"known: {', '.join(sorted(_SETTINGS))}"
        )
    clock: Clock | None = context.clock if isinstance(context.clock, SimClock) else None
    if settings.get("real_time"):
        clock = HostClock() if isinstance(context.clock, SimClock) else context.clock
    return shared_station(
        context,
        clock=clock,
        seed=settings.get("seed"),
        range_m=settings.get("range_m"),
        pitch_deg=settings.get("pitch_deg"),
    )


def lidar_factory(settings: Mapping[str, object], context: DriverContext) -> SimLidar:
    """Factory of the ``sim`` lidar driver."""
    return SimLidar(station_from_context(settings, context))


def turntable_factory(settings: Mapping[str, object], context: DriverContext) -> SimTurntable:
    """Factory of the ``sim`` turntable driver."""
    return SimTurntable(station_from_context(settings, context))


def encoder_factory(settings: Mapping[str, object], context: DriverContext) -> SimEncoder:
    """Factory of the ``sim`` encoder driver."""
    return SimEncoder(station_from_context(settings, context))


for _factory in (lidar_factory, turntable_factory, encoder_factory):
    # the settings model the driver registry checks a recipe's settings with
    _factory.settings_model = SimSettings  # type: ignore[union-attr]
