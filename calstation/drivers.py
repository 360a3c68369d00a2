"""Driver interfaces: what calstation needs from a lidar, a turntable and an encoder.

Drivers are typed protocols: a plugin's class satisfies them by having the methods, no base class
needed. Every timestamp is on one host clock, integer nanoseconds since the Unix epoch (see
:mod:`calstation.clock`); a driver converts its device's own clock before handing data over.

A driver factory (registered through the ``calstation_register_drivers`` hook) is called as
``factory(settings, context)`` with the ``settings`` mapping from the recipe and a
:class:`DriverContext`, and returns an object implementing one of the protocols below.
"""

from __future__ import annotations

import enum
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from calstation.clock import Clock
from calstation.errors import DriverError
from calstation.jsonvalue import JSONObject

DriverKind = Literal["lidar", "turntable", "encoder"]


# --- data ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class LidarInfo:
    """Identity and geometry of a line scanner.

    ``fov_rad`` is the full field of view; ``points_per_line`` the nominal points in one line;
    ``line_rate_hz`` the nominal lines per second; ``range_min_m``/``range_max_m`` the valid range.
    ``extra`` holds anything else the device reports (firmware, serial number, …).
    """

    vendor: str
    model: str
    serial: str
    fov_rad: float
    points_per_line: int
    line_rate_hz: float
    range_min_m: float
    range_max_m: float
    extra: Mapping[str, object] = field(default_factory=dict)

    def as_dict(self) -> dict[str, object]:
        """A JSON-ready mapping."""
        return {
            "vendor": self.vendor,
            "model": self.model,
            "serial": self.serial,
            "fov_rad": self.fov_rad,
            "points_per_line": self.points_per_line,
            "line_rate_hz": self.line_rate_hz,
            "range_min_m": self.range_min_m,
            "range_max_m": self.range_max_m,
            "extra": dict(self.extra),
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> LidarInfo:  # Any: a recording's parsed JSON
        """Inverse of :meth:`as_dict`."""
        return cls(
            vendor=str(d["vendor"]),
            model=str(d["model"]),
            serial=str(d["serial"]),
            fov_rad=float(d["fov_rad"]),
            points_per_line=int(d["points_per_line"]),
            line_rate_hz=float(d["line_rate_hz"]),
            range_min_m=float(d["range_min_m"]),
            range_max_m=float(d["range_max_m"]),
            extra=dict(d.get("extra", {})),
        )


@dataclass(frozen=True, eq=False)
class LidarLine:
    """One line of a line scanner, in the lidar's own polar coordinates (frame L, DESIGN §2).

    - ``timestamp_ns``: host-clock time of the first point (index 0).
    - ``azimuth_rad``: (N,) float, α of each point (0 = +Y_L boresight, positive toward +X_L).
    - ``range_m``: (N,) float, metres; the value of an invalid point is meaningless.
    - ``valid``: (N,) bool; invalid returns (no echo, dropout, out of range) stay in the line,
      marked, so point timing and indexing are never lost.
    - ``point_period_ns``: time between consecutive points; point i is measured at
      ``timestamp_ns + i·point_period_ns`` unless ``time_offset_ns`` gives per-point offsets.
    - ``intensity``: optional (N,) float, device units.
    """

    timestamp_ns: int
    azimuth_rad: NDArray[np.float64]
    range_m: NDArray[np.float64]
    valid: NDArray[np.bool_]
    point_period_ns: float = 0.0
    time_offset_ns: NDArray[np.int64] | None = None
    intensity: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        n = len(self.azimuth_rad)
        if len(self.range_m) != n or len(self.valid) != n:
            raise DriverError(
                f"lidar line arrays differ in length: azimuth {n}, range {len(self.range_m)}, "
                f"valid {len(self.valid)}"
            )
        if self.time_offset_ns is not None and len(self.time_offset_ns) != n:
            raise DriverError(
                f"time_offset_ns has {len(self.time_offset_ns)} values for {n} points"
            )
        if self.intensity is not None and len(self.intensity) != n:
            raise DriverError(f"intensity has {len(self.intensity)} values for {n} points")

    def __len__(self) -> int:
        return len(self.azimuth_rad)

    def point_times_ns(self) -> NDArray[np.int64]:
        """(N,) host-clock time of each point (ns)."""
        if self.time_offset_ns is not None:
            return self.timestamp_ns + np.asarray(self.time_offset_ns, dtype=np.int64)
        offsets = np.round(np.arange(len(self)) * self.point_period_ns).astype(np.int64)
        return self.timestamp_ns + offsets


@dataclass(frozen=True)
class EncoderSample:
    """One encoder reading: host-clock time (ns) and the unwrapped, signed count."""

    timestamp_ns: int
    count: int


class TurntableState(enum.StrEnum):
    """Coarse state of the turntable drive."""

    DISABLED = "disabled"
    ENABLED = "enabled"
    MOVING = "moving"
    FAULT = "fault"
    EMERGENCY_STOP = "emergency_stop"


@dataclass(frozen=True)
class TurntableStatus:
    """What the turntable reports: state, speed (rpm), position (rad, if known) and faults."""

    timestamp_ns: int
    state: TurntableState
    speed_rpm: float
    position_rad: float | None = None
    faults: tuple[str, ...] = ()

    def as_dict(self) -> JSONObject:
        """A JSON-ready mapping."""
        return {
            "timestamp_ns": self.timestamp_ns,
            "state": self.state.value,
            "speed_rpm": self.speed_rpm,
            "position_rad": self.position_rad,
            "faults": list(self.faults),
        }


@dataclass(frozen=True)
class DriverContext:
    """What a driver factory gets besides its own settings; one per run.

    - ``clock``: the host clock drivers stamp data with.
    - ``recipe``: the :class:`~calstation.recipes.LoadedRecipe`, for drivers that need fixture
      geometry (the simulator).
    - ``shared``: a per-run dictionary where the drivers of one plugin keep state they share (the
      simulated lidar, turntable and encoder share one scene through it). Keys are plugin names.

    A driver that runs on a time base of its own (the simulator's, which only advances as data is
    produced) exposes it as a ``clock`` attribute; the station then waits on the lidar's ``clock``
    instead of the host clock.
    """

    clock: Clock
    recipe: Any = None  # Any: a LoadedRecipe, whose type lives in a layer above
    shared: dict[str, Any] = field(default_factory=dict)  # Any: each plugin's own objects


# --- protocols -----------------------------------------------------------------------------
@runtime_checkable
class Lidar(Protocol):
    """A static 2D line scanner."""

    def info(self) -> LidarInfo:
        """Identity and geometry of the device. May talk to the device."""
        ...

    def start(self) -> None:
        """Switch the laser on and start streaming lines."""
        ...

    def stop(self) -> None:
        """Stop streaming (the laser may stay on). Safe to call when not started."""
        ...

    def lines(self) -> Iterator[LidarLine]:
        """Lines in acquisition order, each stamped on the host clock, until :meth:`stop`.

        Raises :class:`~calstation.errors.DeviceTimeout` if the device goes silent.
        """
        ...

    def close(self) -> None:
        """Release the port. Idempotent."""
        ...


@runtime_checkable
class Turntable(Protocol):
    """A motorised turntable (the rotary platform's drive)."""

    def enable(self) -> None:
        """Power the drive and make it ready to move."""
        ...

    def disable(self) -> None:
        """Remove power from the motor (after stopping it)."""
        ...

    def spin(self, rpm: float) -> None:
        """Turn continuously at ``rpm`` (signed: positive = +X_P right-handed). Returns at once."""
        ...

    def move_to(self, angle_rad: float) -> None:
        """Turn to ``angle_rad`` and return when there (or raise on fault / timeout)."""
        ...

    def stop(self) -> None:
        """Decelerate to standstill and return when stopped."""
        ...

    def emergency_stop(self) -> None:
        """Stop now by the fastest means the drive has (quick stop). Never raises."""
        ...

    def status(self) -> TurntableStatus:
        """Current state, speed, position and active faults."""
        ...

    def close(self) -> None:
        """Stop the motor if moving and release the bus. Idempotent."""
        ...


@runtime_checkable
class Encoder(Protocol):
    """An incremental rotary encoder on the platter axis."""

    @property
    def counts_per_revolution(self) -> int:
        """Counts per platter revolution (4·ppr for a quadrature encoder)."""
        ...

    def read(self) -> EncoderSample:
        """One reading now."""
        ...

    def samples(self) -> list[EncoderSample]:
        """All readings taken since the previous call, oldest first (a background stream)."""
        ...

    def close(self) -> None:
        """Release the device. Idempotent."""
        ...
