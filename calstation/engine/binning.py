"""Azimuth-bin smoothing of line scans (paper §IV-A: 0.02° bins, median range per bin).

Many lines of a static scan are merged: every return falls into a fixed azimuth bin and the bin's
range is the median of its returns, which rejects outliers (mixed pixels, dropouts, noise).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calstation.engine.frames import FloatArray, polar_to_lidar
from calstation.errors import CalibrationError


@dataclass(frozen=True)
class BinnedScan:
    """A smoothed scan: one entry per non-empty azimuth bin, in increasing azimuth.

    ``azimuth_rad`` (B,) bin centres, ``range_m`` (B,) median ranges, ``count`` (B,) returns per
    bin, ``bin_rad`` the bin width.
    """

    azimuth_rad: FloatArray
    range_m: FloatArray
    count: NDArray[np.int64]
    bin_rad: float

    def __len__(self) -> int:
        return int(self.azimuth_rad.shape[0])

    def points(self) -> FloatArray:
        """(B, 2) points (x_L, y_L) in the scan plane, metres."""
        return polar_to_lidar(self.range_m, self.azimuth_rad)[:, :2]


def azimuth_bin_median(
    azimuth_rad: ArrayLike,
    range_m: ArrayLike,
    valid: ArrayLike | None = None,
    *,
    bin_deg: float = 0.02,
    min_count: int = 1,
) -> BinnedScan:
    """Median range per azimuth bin over all returns given (any number of lines).

    ``azimuth_rad`` and ``range_m`` are (M,) arrays (radians, metres); ``valid`` an optional (M,)
    mask. Bins are ``bin_deg`` wide, aligned to azimuth 0; bins with fewer than ``min_count``
    valid returns are dropped. The median of an even count is the mean of the two middle values.
    """
    az = np.asarray(azimuth_rad, dtype=np.float64).reshape(-1)
    rng = np.asarray(range_m, dtype=np.float64).reshape(-1)
    if az.shape != rng.shape:
        raise CalibrationError(
            f"azimuth and range differ in length: {az.shape[0]} vs {rng.shape[0]}"
        )
    if not bin_deg > 0:
        raise CalibrationError(f"azimuth bin width must be positive, got {bin_deg}°")
    ok = np.isfinite(az) & np.isfinite(rng) & (rng > 0)
    if valid is not None:
        v = np.asarray(valid, dtype=bool).reshape(-1)
        if v.shape != az.shape:
            raise CalibrationError("valid mask differs in length from the returns")
        ok &= v
    bin_rad = math.radians(bin_deg)
    az, rng = az[ok], rng[ok]
    if az.size == 0:
        empty = np.zeros(0)
        return BinnedScan(empty, empty.copy(), np.zeros(0, dtype=np.int64), bin_rad)
    idx = np.floor(az / bin_rad + 0.5).astype(np.int64)
    order = np.lexsort((rng, idx))
    idx, rng = idx[order], rng[order]
    starts = np.flatnonzero(np.r_[True, idx[1:] != idx[:-1]])
    counts = np.diff(np.r_[starts, idx.size])
    lo = starts + (counts - 1) // 2
    hi = starts + counts // 2
    med = 0.5 * (rng[lo] + rng[hi])
    keep = counts >= min_count
    return BinnedScan(
        azimuth_rad=idx[starts][keep] * bin_rad,
        range_m=med[keep],
        count=counts[keep].astype(np.int64),
        bin_rad=bin_rad,
    )
