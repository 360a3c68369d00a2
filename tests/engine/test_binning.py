"""Azimuth-bin median smoothing."""

from __future__ import annotations

import math

import numpy as np
import pytest

from calstation.engine.binning import azimuth_bin_median
from calstation.errors import CalibrationError


def test_median_per_bin_rejects_outliers() -> None:
    bin_rad = math.radians(0.02)
    az = np.repeat(np.arange(5) * bin_rad, 7)
    rng = np.tile([1.0, 1.001, 0.999, 1.0, 5.0, 1.0005, 0.2], 5) + np.repeat(np.arange(5), 7)
    b = azimuth_bin_median(az, rng, bin_deg=0.02)
    assert len(b) == 5
    np.testing.assert_allclose(b.azimuth_rad, np.arange(5) * bin_rad)
    np.testing.assert_allclose(b.range_m, 1.0 + np.arange(5))
    assert (b.count == 7).all()


def test_even_count_median_is_mean_of_middle_pair() -> None:
    b = azimuth_bin_median([0.0, 0.0, 0.0, 0.0], [1.0, 2.0, 3.0, 10.0])
    assert b.range_m.tolist() == [2.5]


def test_invalid_and_nonfinite_returns_are_ignored() -> None:
    az = np.zeros(4)
    rng = np.array([1.0, np.nan, 0.0, 3.0])
    b = azimuth_bin_median(az, rng, valid=[True, True, True, False])
    assert b.range_m.tolist() == [1.0]
    empty = azimuth_bin_median(az, rng, valid=[False] * 4)
    assert len(empty) == 0 and empty.points().shape == (0, 2)


def test_bad_input_raises() -> None:
    with pytest.raises(CalibrationError, match="differ in length"):
        azimuth_bin_median([0.0, 1.0], [1.0])
    with pytest.raises(CalibrationError, match="positive"):
        azimuth_bin_median([0.0], [1.0], bin_deg=0)


def test_points_follow_the_lidar_convention() -> None:
    b = azimuth_bin_median([0.0, math.pi / 2], [2.0, 3.0], bin_deg=1.0)
    np.testing.assert_allclose(b.points(), [[0.0, 2.0], [3.0, 0.0]], atol=1e-12)
