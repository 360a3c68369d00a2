"""A scan as the engine takes it: lidar returns with their times, and the encoder's readings.

:class:`Scan` is arrays and the few numbers needed to turn a return into a point with its platter
angle; it knows nothing of files. The recordings layer reads an MCAP file into a
:class:`calstation.recordings.recorded.Recording`, which *is* a :class:`Scan` with the file's
metadata beside it, so every engine function takes a recording as it is. A notebook or a port
builds a :class:`Scan` from its own arrays.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Self

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calstation.engine.frames import counts_to_angle
from calstation.errors import RecordingError


def encoder_angle(
    t_ns: NDArray[np.int64],
    encoder_t_ns: NDArray[np.int64],
    encoder_count: NDArray[np.int64],
    counts_per_revolution: int,
    encoder_direction: int,
    encoder_latency_s: float,
) -> NDArray[np.float64]:
    """Platter angle φ (rad, unwrapped) at lidar times ``t_ns`` from encoder readings in time
    order (at least one), as :meth:`Scan.platter_angle` describes: linear interpolation of
    the counts after shifting the encoder's times by its latency; NaN outside the readings'
    span unless the platter never moved."""
    counts = encoder_count.astype(np.float64)
    if np.all(encoder_count == encoder_count[0]):
        phi0 = counts_to_angle(counts[0], counts_per_revolution, encoder_direction)
        return np.full(t_ns.shape, float(phi0))
    t0 = int(encoder_t_ns[0])
    latency_ns = round(encoder_latency_s * 1e9)
    enc_s = (encoder_t_ns - t0 - latency_ns).astype(np.float64) * 1e-9
    query_s = (t_ns - t0).astype(np.float64) * 1e-9
    c = np.interp(query_s, enc_s, counts, left=np.nan, right=np.nan)
    return counts_to_angle(c, counts_per_revolution, encoder_direction)




@dataclass(frozen=True, kw_only=True)
class Scan:
    """Lidar returns and encoder readings as flat arrays (one entry per return, valid or not).

    Times are host-clock ns since the Unix epoch (the lidar's time base); angles radians; ranges
    metres. Arrays:

    - ``line_timestamp_ns`` (L,): time of the first return of each line.
    - ``line_index`` (M,) int32: the line of each return; ``t_ns`` (M,): time of each return.
    - ``azimuth_rad``, ``range_m``, ``valid``, ``intensity`` (M,) (intensity None if absent).
    - ``encoder_t_ns``, ``encoder_count`` (K,): encoder readings in time order, on the encoder's
      clock, ``encoder_latency_s`` (encoder time minus lidar time) after the lidar's.
    - ``line_point_period_ns`` (L,) and ``line_has_offsets`` (L,): each line's return period and
      whether it carried explicit per-return offsets (None when not known).

    ``path`` names where the scan came from, for messages.
    """

    path: Path = Path("<scan>")
    counts_per_revolution: int
    encoder_direction: int
    encoder_latency_s: float
    line_timestamp_ns: NDArray[np.int64]
    line_index: NDArray[np.int32]
    t_ns: NDArray[np.int64]
    azimuth_rad: NDArray[np.float64]
    range_m: NDArray[np.float64]
    valid: NDArray[np.bool_]
    intensity: NDArray[np.float64] | None = None
    encoder_t_ns: NDArray[np.int64]
    encoder_count: NDArray[np.int64]
    line_point_period_ns: NDArray[np.float64] | None = None
    line_has_offsets: NDArray[np.bool_] | None = None

    # --- summaries -----------------------------------------------------------------------
    @property
    def n_lines(self) -> int:
        """Number of lidar lines L."""
        return len(self.line_timestamp_ns)

    @property
    def n_points(self) -> int:
        """Number of points M (valid or not)."""
        return len(self.t_ns)

    def with_encoder_latency(self, latency_s: float) -> Self:
        """The same scan read with another encoder latency (encoder time minus lidar time, s):
        an estimated one (:mod:`calstation.engine.timeoffset`) in place of the configured one."""
        if not math.isfinite(latency_s):
            raise RecordingError(f"encoder latency must be finite, got {latency_s}")
        if latency_s == self.encoder_latency_s:
            return self
        return replace(self, encoder_latency_s=float(latency_s))

    def whole_turns(self) -> int:
        """Whole revolutions of the platter between the first and the last line (0 without
        encoder readings covering them)."""
        if self.n_lines < 2 or len(self.encoder_t_ns) == 0:
            return 0
        ends = np.array([self.line_timestamp_ns[0], self.line_timestamp_ns[-1]], dtype=np.int64)
        phi = self.platter_angle(ends)
        if not np.all(np.isfinite(phi)):
            return 0
        return max(0, math.floor(abs(float(phi[1] - phi[0])) / (2 * math.pi) + 0.02))

    def first_turns(self, turns: float) -> Self:
        """The same scan cut after its first ``turns`` turns of the platter (whole lines, from
        the first line on): what a shorter scan of the same scene would have recorded."""
        if self.n_lines == 0 or len(self.encoder_t_ns) == 0:
            return self
        phi = self.platter_angle(self.line_timestamp_ns)
        start = phi[0] if np.isfinite(phi[0]) else np.nanmin(phi)
        keep_lines = np.flatnonzero(np.abs(phi - start) <= turns * 2 * math.pi)
        return self.first_lines(int(keep_lines.max()) + 1 if keep_lines.size else 0)

    def first_lines(self, lines: int) -> Self:
        """The same scan cut after its first ``lines`` lines (itself when it has no more)."""
        if lines >= self.n_lines:
            return self
        last = max(0, lines)
        end = int(self.line_bounds()[last])
        period, offsets = self.line_point_period_ns, self.line_has_offsets
        return replace(
            self, line_timestamp_ns=self.line_timestamp_ns[:last],
            line_index=self.line_index[:end], t_ns=self.t_ns[:end],
            azimuth_rad=self.azimuth_rad[:end], range_m=self.range_m[:end],
            valid=self.valid[:end],
            intensity=None if self.intensity is None else self.intensity[:end],
            line_point_period_ns=None if period is None else period[:last],
            line_has_offsets=None if offsets is None else offsets[:last],
        )

    # --- geometry ------------------------------------------------------------------------
    def platter_angle(self, t_ns: ArrayLike) -> NDArray[np.float64]:
        """Platter angle φ (rad) at host-clock times ``t_ns`` (lidar time base), shape of input.

        The encoder counts are interpolated linearly in time, after shifting the encoder's
        timestamps by ``encoder_latency_s`` (encoder time minus lidar time) onto the lidar's time
        base, then converted with the encoder direction and counts per revolution. φ is unwrapped
        (it keeps growing over several turns). Times outside the encoder's span give NaN — except
        when every reading has the same count (a platter at rest), which holds for all times.
        Raises :class:`RecordingError` if the recording has no encoder readings.
        """
        t = np.asarray(t_ns, dtype=np.int64)
        if len(self.encoder_t_ns) == 0:
            raise RecordingError(
                f"recording {self.path} has no encoder readings: the platter angle is unknown"
            )
        return encoder_angle(
            t,
            self.encoder_t_ns,
            self.encoder_count,
            self.counts_per_revolution,
            self.encoder_direction,
            self.encoder_latency_s,
        )

    def points_lidar(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Valid points with a known platter angle: ((N, 3) in frame L, metres; (N,) φ, rad).

        Invalid returns and points outside the encoder's time span (φ NaN) are left out.
        """
        p_L, phi, _, _ = self.valid_returns()
        return p_L, phi

    def valid_returns(
        self,
    ) -> tuple[
        NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]
    ]:
        """As :meth:`points_lidar`, plus the same returns' (N,) ranges (m) and azimuths (rad)
        as measured: ``(p_L, φ, range, azimuth)``."""
        idx = np.flatnonzero(self.valid)
        phi = self.platter_angle(self.t_ns[idx])
        keep = np.isfinite(phi)
        if not keep.all():
            idx, phi = idx[keep], phi[keep]
        rng = self.range_m[idx]
        az = self.azimuth_rad[idx]
        # same as frames.polar_to_lidar, filled in place (this runs on millions of points)
        p_L = np.zeros((len(idx), 3))
        np.multiply(rng, np.sin(az), out=p_L[:, 0])
        np.multiply(rng, np.cos(az), out=p_L[:, 1])
        return p_L, phi, rng, az

    def line_bounds(self) -> NDArray[np.int64]:
        """(L+1,) offsets: the points of line i are ``[bounds[i], bounds[i+1])``."""
        counts = np.bincount(self.line_index, minlength=self.n_lines)
        bounds = np.zeros(self.n_lines + 1, dtype=np.int64)
        np.cumsum(counts, out=bounds[1:])
        return bounds
