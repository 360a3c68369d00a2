"""The platter's motion: commanded speed with an acceleration ramp and a speed ripple, exactly.

The nominal motion is piecewise: each command ramps linearly (constant acceleration) from the
speed at the moment of the command to the new speed, then holds it, so the nominal angle φₙ(t) is
piecewise quadratic. The ripple is locked to the platter angle (``cycles`` per revolution, a
motor's cogging or a worn gear): ``ω = ωₙ·(1 + a·sin(k·φₙ))``, which integrates in closed form to

    φ(t) = φₙ(t) + (a/k)·(1 − cos(k·φₙ(t))).

So φ is analytic at every instant (no integration error, identical for any query pattern).
Times are seconds since the station's time origin; angles radians, right-handed about +X_P.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


def rpm_to_rad_s(rpm: float) -> float:
    """Revolutions per minute → rad/s."""
    return rpm * 2.0 * math.pi / 60.0


@dataclass(frozen=True)
class _Segment:
    t0: float  # s, start of the segment
    phi0: float  # nominal angle at t0 (rad)
    w0: float  # speed at t0 (rad/s)
    w1: float  # commanded speed (rad/s)
    accel: float  # |acceleration| (rad/s²) of the ramp

    @property
    def ramp_s(self) -> float:
        return abs(self.w1 - self.w0) / self.accel


class PlatterMotion:
    """Angle and speed of the platter as functions of time (seconds since the time origin).

    ``acceleration`` in rad/s² (ramps), ``ripple`` the relative speed ripple amplitude,
    ``cycles`` the ripple cycles per revolution (0 disables the ripple).
    """

    def __init__(self, acceleration: float, ripple: float = 0.0, cycles: int = 0) -> None:
        if acceleration <= 0:
            raise ValueError("acceleration must be positive")
        self.acceleration = acceleration
        self.ripple = ripple if cycles > 0 else 0.0
        self.cycles = cycles
        self._segments: list[_Segment] = [_Segment(0.0, 0.0, 0.0, 0.0, acceleration)]
        self._t0 = np.array([0.0])
        self._lock = threading.RLock()  # real-time emulators command and query from threads

    # --- commands -------------------------------------------------------------------------
    def command(self, t: float, speed: float, acceleration: float | None = None) -> float:
        """Command ``speed`` (rad/s) at time ``t`` (s); returns when the ramp ends (s).

        ``t`` earlier than the previous command is moved up to it (time never runs backwards).
        """
        with self._lock:
            t = max(t, self._segments[-1].t0)
            phi_n, w = self._nominal_scalar(t)
            seg = _Segment(t, phi_n, w, speed, acceleration or self.acceleration)
            if t == self._segments[-1].t0:
                self._segments[-1] = seg
            else:
                self._segments.append(seg)
            self._t0 = np.array([s.t0 for s in self._segments])
            return t + seg.ramp_s

    @property
    def last_command_time(self) -> float:
        """Time (s) of the latest command."""
        return self._segments[-1].t0

    def commanded_speed(self) -> float:
        """The latest commanded speed (rad/s)."""
        return self._segments[-1].w1

    def stop_time(self) -> float:
        """When the latest ramp ends (s)."""
        s = self._segments[-1]
        return s.t0 + s.ramp_s

    # --- evaluation -----------------------------------------------------------------------
    def _nominal_scalar(self, t: float) -> tuple[float, float]:
        phi, w = self.nominal(np.array([t]))
        return float(phi[0]), float(w[0])

    def nominal(self, t: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Nominal angle φₙ (rad) and speed ωₙ (rad/s) at times ``t`` (s), without ripple."""
        tt = np.asarray(t, dtype=np.float64)
        with self._lock:
            segs, starts = list(self._segments), self._t0
        idx = np.clip(np.searchsorted(starts, tt, side="right") - 1, 0, None)
        t0 = starts[idx]
        phi0 = np.array([s.phi0 for s in segs])[idx]
        w0 = np.array([s.w0 for s in segs])[idx]
        w1 = np.array([s.w1 for s in segs])[idx]
        acc = np.array([s.accel for s in segs])[idx] * np.sign(w1 - w0)
        ramp = np.array([s.ramp_s for s in segs])[idx]
        tau = np.maximum(tt - t0, 0.0)
        tr = np.minimum(tau, ramp)
        phi = phi0 + w0 * tr + 0.5 * acc * tr * tr + w1 * (tau - tr)
        w = np.where(tau < ramp, w0 + acc * tau, w1)
        return phi, w

    def angle(self, t: ArrayLike) -> FloatArray:
        """True platter angle φ (rad, unwrapped) at times ``t`` (s)."""
        phi_n, _ = self.nominal(t)
        if self.ripple == 0.0:
            return phi_n
        k = float(self.cycles)
        return np.asarray(phi_n + (self.ripple / k) * (1.0 - np.cos(k * phi_n)), dtype=np.float64)

    def speed(self, t: ArrayLike) -> FloatArray:
        """True platter speed dφ/dt (rad/s) at times ``t`` (s)."""
        phi_n, w_n = self.nominal(t)
        if self.ripple == 0.0:
            return w_n
        return np.asarray(w_n * (1.0 + self.ripple * np.sin(self.cycles * phi_n)), dtype=np.float64)
