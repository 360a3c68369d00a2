"""PCA split-and-merge line segments."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from calstation.engine.lines import fit_line, intersect_lines, segment_profile, split_at_gaps
from calstation.errors import CalibrationError


def _polyline(corners: list[tuple[float, float]], step: float) -> np.ndarray:
    pts = []
    for (x0, y0), (x1, y1) in itertools.pairwise(corners):
        n = max(2, round(math.hypot(x1 - x0, y1 - y0) / step))
        t = np.linspace(0, 1, n, endpoint=False)
        pts.append(np.column_stack([x0 + t * (x1 - x0), y0 + t * (y1 - y0)]))
    pts.append(np.array([corners[-1]]))
    return np.vstack(pts)


def test_l_profile_gives_two_segments_with_their_lengths() -> None:
    rng = np.random.default_rng(0)
    p = _polyline([(0.0, 0.0), (0.15, 0.0), (0.15, 0.10)], 0.0015)
    p = p + rng.normal(0, 0.0002, p.shape)
    segs = segment_profile(p, tolerance=0.002, min_points=8)
    assert len(segs) == 2
    assert segs[0].length == pytest.approx(0.15, abs=0.003)
    assert segs[1].length == pytest.approx(0.10, abs=0.003)
    assert abs(abs(float(np.dot(segs[0].direction, segs[1].direction)))) < 0.02
    corner = intersect_lines(
        segs[0].centroid, segs[0].direction, segs[1].centroid, segs[1].direction
    )
    np.testing.assert_allclose(corner, [0.15, 0.0], atol=0.001)


def test_gap_splits_and_short_pieces_are_dropped() -> None:
    a = _polyline([(0.0, 0.0), (0.1, 0.0)], 0.001)
    b = _polyline([(0.2, 0.0), (0.3, 0.0)], 0.001)
    stray = np.array([[0.15, 0.05], [0.151, 0.05]])
    p = np.vstack([a, stray, b])
    assert len(split_at_gaps(p, 0.01)) == 3
    segs = segment_profile(p, tolerance=0.002, min_points=8, max_gap=0.01)
    assert len(segs) == 2
    assert all(s.length == pytest.approx(0.1, abs=0.002) for s in segs)


def test_collinear_pieces_are_merged_after_splitting() -> None:
    # a long straight run with one bump forces splits; the straight parts stay one segment each
    p = _polyline([(0.0, 0.0), (0.3, 0.0)], 0.001)
    segs = segment_profile(p, tolerance=0.001, min_points=5)
    assert len(segs) == 1 and segs[0].n == p.shape[0]


def test_fit_line_residuals_and_errors() -> None:
    _c, d, res = fit_line([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]])
    np.testing.assert_allclose(d, [math.sqrt(0.5)] * 2)
    np.testing.assert_allclose(res, 0.0, atol=1e-12)
    with pytest.raises(CalibrationError):
        fit_line([[0.0, 0.0]])
    with pytest.raises(CalibrationError, match="parallel"):
        intersect_lines([0, 0], [1, 0], [0, 1], [1, 0])
