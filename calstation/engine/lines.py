"""Contiguous straight segments in an ordered 2D profile (paper §IV-A, FindContiguousLines).

Split-and-merge with PCA line fits: the profile is first cut at range jumps, then each piece is
split recursively at the point farthest from its PCA line until every piece is straight within
the tolerance, and finally neighbouring pieces that are collinear are merged back.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from calstation.engine.frames import FloatArray
from calstation.errors import CalibrationError


@dataclass(frozen=True)
class Segment:
    """A straight segment fitted to points ``start:stop`` of a profile (scan plane, metres).

    ``centroid`` (2,), ``direction`` (2,) unit vector from the first point toward the last,
    ``p0``/``p1`` (2,) the first and last points projected onto the line, ``rms`` the RMS
    perpendicular residual, ``n`` the number of points.
    """

    start: int
    stop: int
    centroid: FloatArray
    direction: FloatArray
    p0: FloatArray
    p1: FloatArray
    rms: float
    n: int

    @property
    def length(self) -> float:
        """Distance between the projected end points, metres."""
        return float(np.linalg.norm(self.p1 - self.p0))

    @property
    def angle_deg(self) -> float:
        """Direction angle in the scan plane, degrees from +X_L toward +Y_L."""
        return math.degrees(math.atan2(self.direction[1], self.direction[0]))

    def describe(self) -> str:
        """One line for error messages: length, direction, ends (mm / degrees)."""
        return (
            f"{self.length * 1e3:.1f} mm at {self.angle_deg:.1f}° from "
            f"({self.p0[0] * 1e3:.0f}, {self.p0[1] * 1e3:.0f}) to "
            f"({self.p1[0] * 1e3:.0f}, {self.p1[1] * 1e3:.0f}) mm, {self.n} pts, "
            f"rms {self.rms * 1e3:.2f} mm"
        )


def fit_line(points: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
    """PCA line through (N, 2) points: (centroid (2,), unit direction (2,), residuals (N,)).

    The direction points from the first point toward the last; residuals are signed
    perpendicular distances, metres.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2 or p.shape[0] < 2:
        raise CalibrationError(f"a line fit needs (N ≥ 2, 2) points, got shape {p.shape}")
    c = p.mean(axis=0)
    q = p - c
    _, _, vt = np.linalg.svd(q, full_matrices=False)
    d = vt[0]
    if np.dot(p[-1] - p[0], d) < 0:
        d = -d
    normal = np.array([-d[1], d[0]])
    return c, d, q @ normal


def _segment(points: FloatArray, start: int, stop: int) -> Segment:
    c, d, res = fit_line(points[start:stop])
    p0 = c + d * float(np.dot(points[start] - c, d))
    p1 = c + d * float(np.dot(points[stop - 1] - c, d))
    rms = float(np.sqrt(np.mean(res**2)))
    return Segment(start, stop, c, d, p0, p1, rms, stop - start)


def split_at_gaps(points: ArrayLike, max_gap: float) -> list[tuple[int, int]]:
    """Index ranges [start, stop) of runs whose consecutive points are at most ``max_gap`` apart."""
    p = np.asarray(points, dtype=np.float64)
    if p.shape[0] == 0:
        return []
    step = np.linalg.norm(np.diff(p, axis=0), axis=1)
    cuts = np.flatnonzero(step > max_gap) + 1
    bounds = np.r_[0, cuts, p.shape[0]]
    return [(int(a), int(b)) for a, b in itertools.pairwise(bounds)]


def segment_profile(
    points: ArrayLike,
    *,
    tolerance: float = 0.002,
    min_points: int = 8,
    max_gap: float = 0.02,
    merge_angle_deg: float = 2.0,
) -> list[Segment]:
    """Straight segments of an ordered (N, 2) profile (scan-plane points in azimuth order).

    Pieces are split at range jumps larger than ``max_gap`` (m), then split recursively at the
    farthest point while the largest perpendicular deviation exceeds ``tolerance`` (m);
    neighbours that touch, differ in direction by less than ``merge_angle_deg`` and fit one line
    within ``tolerance`` are merged. Pieces with fewer than ``min_points`` points are dropped.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2:
        raise CalibrationError(f"a profile must be (N, 2) points, got shape {p.shape}")
    pieces: list[tuple[int, int]] = []
    # small pieces are kept until after merging: a split may cut a long segment anywhere
    stack = [r for r in split_at_gaps(p, max_gap) if r[1] - r[0] >= 2]
    while stack:
        a, b = stack.pop()
        if b - a <= 2:
            pieces.append((a, b))
            continue
        _, _, res = fit_line(p[a:b])
        worst = int(np.argmax(np.abs(res)))
        if abs(res[worst]) <= tolerance:
            pieces.append((a, b))
            continue
        # split at the farthest point from the chord (a robust corner locator), not the PCA line
        chord = p[b - 1] - p[a]
        norm = np.linalg.norm(chord)
        if norm > 0:
            nrm = np.array([-chord[1], chord[0]]) / norm
            k = a + int(np.argmax(np.abs((p[a:b] - p[a]) @ nrm)))
        else:
            k = a + worst
        k = min(max(k, a + 1), b - 1)
        stack.extend(r for r in ((a, k), (k, b)) if r[1] - r[0] >= 2)
    pieces.sort()
    segments = [_segment(p, a, b) for a, b in pieces]
    merged: list[Segment] = []
    for seg in segments:
        if merged:
            prev = merged[-1]
            touching = (
                seg.start - prev.stop <= 1
                and float(np.linalg.norm(p[seg.start] - p[prev.stop - 1])) <= max_gap
            )
            cosang = abs(float(np.dot(prev.direction, seg.direction)))
            # tiny pieces have no reliable direction: only the joined fit decides for them
            small = min(prev.n, seg.n) < min_points
            if touching and (small or cosang >= math.cos(math.radians(merge_angle_deg))):
                joined = _segment(p, prev.start, seg.stop)
                _, _, res = fit_line(p[prev.start : seg.stop])
                if float(np.max(np.abs(res))) <= tolerance:
                    merged[-1] = joined
                    continue
        merged.append(seg)
    kept = [s for s in merged if s.n >= min_points]
    return [_grow(p, s, tolerance, max_gap) for s in kept]


def _grow(points: FloatArray, seg: Segment, tolerance: float, max_gap: float) -> Segment:
    """Extend a segment over neighbouring points that lie on its line.

    Recursive splitting may hand the last points before a corner to the neighbour; a point
    within max(4·rms, 0.5 mm) of the line (at most ``tolerance``) belongs to the segment.
    """
    thr = min(tolerance, max(4.0 * seg.rms, 0.0005))
    normal = np.array([-seg.direction[1], seg.direction[0]])

    def on_line(i: int, j: int) -> bool:
        near = abs(float(np.dot(points[i] - seg.centroid, normal))) <= thr
        return near and float(np.linalg.norm(points[i] - points[j])) <= max_gap

    start, stop = seg.start, seg.stop
    while start > 0 and on_line(start - 1, start):
        start -= 1
    while stop < points.shape[0] and on_line(stop, stop - 1):
        stop += 1
    if (start, stop) == (seg.start, seg.stop):
        return seg
    grown = _segment(points, start, stop)
    return grown if grown.rms <= max(seg.rms * 1.5, thr) else seg


def intersect_lines(c1: ArrayLike, d1: ArrayLike, c2: ArrayLike, d2: ArrayLike) -> FloatArray:
    """Intersection (2,) of the lines c1 + s·d1 and c2 + u·d2 (scan plane, metres)."""
    a = np.column_stack([np.asarray(d1, float), -np.asarray(d2, float)])
    if abs(np.linalg.det(a)) < 1e-9:
        raise CalibrationError("the two lines are parallel; they have no corner")
    s, _ = np.linalg.solve(a, np.asarray(c2, float) - np.asarray(c1, float))
    out: FloatArray = np.asarray(c1, float) + s * np.asarray(d1, float)
    return out
