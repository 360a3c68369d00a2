"""The targetless start: an initial calibration from the spin scan alone, without the L-target.

The platter is a disk turning in its own plane, so its top surface sits at the same place in
the scan plane all through a spin scan: a straight chord whose ends are the platter's rim
(whatever stands on the platter hides its middle for part of the turn, but not the parts near
the rim). With ry ≈ 0 (the initial calibration's assumption, paper Assumption 1), the chord's
direction gives rz, its midpoint tx and ty (the origin on the platter top, the periodicity
gauge), and its length |tz|: ``length = 2·√(R² − tz²)``. tz itself (its sign, and whether a
short chord means |tz| or only a blurred rim) and ry are left to the fine-tuning, which is run
from each candidate start — tz = 0, +|tz|, −|tz|
(:func:`calstation.pipeline.stages.fine_tune`): the one with the lowest cost
is kept.

A scan where no such chord is seen — the rim out of the field of view or hidden, the platter
out of range — fails with :class:`~calstation.errors.InitialCalibrationError`, saying what
was seen and what was expected.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from calstation.engine.frames import Extrinsics, FloatArray
from calstation.engine.lines import Segment, fit_line, segment_profile
from calstation.engine.settings import InitialSettings, PlatterGeometry
from calstation.errors import InitialCalibrationError

if TYPE_CHECKING:
    from calstation.engine.result import CalibrationResult
    from calstation.engine.scan import Scan
    from calstation.engine.spinscan import SpinScan

BIN_DEG = 0.05
"""Azimuth bins of the static profile (degrees)."""

MIN_BIN_RETURNS = 3
COLLINEAR_DEG = 1.5
COLLINEAR_M = 0.004
"""Two segments are one chord when their directions differ by less than COLLINEAR_DEG and each
lies within COLLINEAR_M of the line through both."""

LENGTH_SLACK_M = 0.008
"""A chord may be this much longer than the platter's diameter (rim edges, mixed pixels)."""

MIN_LENGTH_FRACTION = 0.5
"""… and no shorter than this fraction of the diameter (|tz| up to 0.87 R)."""

TZ_SIGN_MIN_M = 0.01
"""Below this |tz| from the chord, one start (tz = 0); above it, three: 0, +|tz| and −|tz|. The
chord's length changes by only tz²/R, and a chord comes out a few millimetres short of the
rim-to-rim length (the rim's edge bins, mixed pixels), which reads as |tz| of 10–60 mm for a
centred axis: 0 stays a candidate."""


@dataclass(frozen=True)
class PlatterChord:
    """The platter's top seen in the scan plane: the rim ends ``a`` and ``b`` (L, metres, in
    azimuth order), the segments that make it, and the RMS of the returns about its line."""

    a: FloatArray
    b: FloatArray
    segments: tuple[Segment, ...]
    rms: float

    @property
    def length(self) -> float:
        return float(np.linalg.norm(self.b - self.a))

    @property
    def midpoint(self) -> FloatArray:
        out: FloatArray = 0.5 * (self.a + self.b)
        return out

    def describe(self) -> str:
        """One line: length, ends (mm), segments."""
        return (f"{self.length * 1e3:.1f} mm from ({self.a[0] * 1e3:.0f}, {self.a[1] * 1e3:.0f}) "
                f"to ({self.b[0] * 1e3:.0f}, {self.b[1] * 1e3:.0f}) mm in "
                f"{len(self.segments)} segment(s), rms {self.rms * 1e3:.2f} mm")


def static_profile(
    az: FloatArray, rng: FloatArray, static: np.ndarray
) -> tuple[FloatArray, FloatArray]:
    """The median range of the static returns per azimuth bin: ((B,) azimuths, (B, 2) points
    in the scan plane)."""
    from calstation.engine.binning import azimuth_bin_median

    binned = azimuth_bin_median(az[static], rng[static], bin_deg=BIN_DEG,
                                min_count=MIN_BIN_RETURNS)
    return binned.azimuth_rad, binned.points()


def _rim_end(
    pts: FloatArray, az: FloatArray, end: int, outward: int, fov: tuple[float, float],
    centroid: FloatArray, normal: FloatArray,
) -> int | None:
    """The last bin of the chord going ``outward`` (±1) from bin ``end``, when the profile then
    leaves the chord's line (the rim's edge, then the floor or nothing): the bins that still lie
    on the line are the chord's. None when the chord runs into the edge of the field of view,
    where its true end (the rim) is not seen."""
    k = end
    while True:
        nxt = k + outward
        if not 0 <= nxt < len(az) or abs(az[nxt] - az[k]) > 3 * math.radians(BIN_DEG):
            break  # nothing (static) beyond: the rim, unless the view ends here
        if abs(float(np.dot(pts[nxt] - centroid, normal))) > COLLINEAR_M:
            break
        k = nxt
    beyond = az[k] + outward * 2 * math.radians(BIN_DEG)
    return k if fov[0] <= beyond <= fov[1] else None


def _candidate(
    pts: FloatArray, az: FloatArray, segs: list[Segment], i: int, j: int,
    fov: tuple[float, float], diameter: float,
) -> PlatterChord | None:
    """The chord made of segments ``i`` … ``j`` (their outer ends the rim), or None."""
    s, t = segs[i], segs[j]
    if abs(float(np.dot(s.direction, t.direction))) < math.cos(math.radians(COLLINEAR_DEG)):
        return None
    idx = np.r_[s.start:s.stop, t.start:t.stop] if i != j else np.arange(s.start, s.stop)
    centroid, direction, _ = fit_line(pts[idx])
    normal = np.array([-direction[1], direction[0]])
    for seg in (s, t):
        if abs(float(np.dot(seg.centroid - centroid, normal))) > COLLINEAR_M:
            return None
    # the rim ends: the outermost bins on the chord's line, projected on it
    first = _rim_end(pts, az, s.start, -1, fov, centroid, normal)
    last = _rim_end(pts, az, t.stop - 1, +1, fov, centroid, normal)
    if first is None or last is None:
        return None
    a = centroid + np.dot(pts[first] - centroid, direction) * direction
    b = centroid + np.dot(pts[last] - centroid, direction) * direction
    length = float(np.linalg.norm(b - a))
    if not MIN_LENGTH_FRACTION * diameter <= length <= diameter + LENGTH_SLACK_M:
        return None
    off = np.abs((pts[idx] - centroid) @ normal)
    return PlatterChord(a=a, b=b, segments=(s,) if i == j else (s, t),
                        rms=float(np.sqrt(np.mean(off**2))))


def find_platter_chord(
    az: FloatArray,
    rng: FloatArray,
    static: np.ndarray,
    platter: PlatterGeometry,
    fov: tuple[float, float],
    settings: InitialSettings,
) -> PlatterChord:
    """The platter's chord in a spin scan's static returns ((N,) azimuths, ranges, static
    mask); ``fov`` the scan's azimuth extent (rad). Raises :class:`InitialCalibrationError`
    with what was seen when no straight, rim-ended chord of a plausible length is found."""
    baz, pts = static_profile(az, rng, static)
    expected = (f"expected the platter's top as a straight chord of {platter.diameter * 1e3:.0f} "
                f"mm at most, ending at its rim on both sides, inside the field of view")
    if len(baz) < 2 * settings.min_segment_points:
        raise InitialCalibrationError(
            f"the spin scan has {len(baz)} azimuth bins of returns that stay put over the turn; "
            f"{expected}. Is the platter in view and turning?"
        )
    spacing = float(np.median(np.linalg.norm(np.diff(pts, axis=0), axis=1)))
    segs = segment_profile(pts, tolerance=settings.line_tolerance,
                           min_points=settings.min_segment_points,
                           max_gap=max(0.01, 8.0 * spacing))
    best: PlatterChord | None = None
    for i in range(len(segs)):
        for j in range(i, len(segs)):
            c = _candidate(pts, baz, segs, i, j, fov, platter.diameter)
            # the nearest plausible chord: the platter stands in front of the floor and walls
            if c is not None and (best is None or _range(c) < _range(best)):
                best = c
    if best is None:
        seen = "; ".join(s.describe() for s in segs[:8]) or "no straight segment"
        raise InitialCalibrationError(
            f"no platter chord in the spin scan: {expected}. Seen in the returns that stay put: "
            f"{seen}. Check that the whole platter, rim to rim, is in the lidar's view and not "
            "hidden, or use the L-target (calibration.start: l_target)"
        )
    return best


def _range(c: PlatterChord) -> float:
    return float(np.linalg.norm(c.midpoint))


def extrinsics_from_chord(chord: PlatterChord, radius: float) -> tuple[Extrinsics, float]:
    """(H with ry = 0 and tz = +|tz|, |tz|) from the platter's chord; the axis points away from
    the platter toward the side of the lidar."""
    u = (chord.b - chord.a) / chord.length
    axis = np.array([-u[1], u[0]])
    m = chord.midpoint
    if float(np.dot(axis, -m)) < 0:
        axis = -axis
    rz = math.atan2(axis[1], axis[0])
    half = 0.5 * chord.length
    tz = math.sqrt(max(radius * radius - half * half, 0.0))
    return Extrinsics(tx=float(m[0]), ty=float(m[1]), tz=tz, rx=0.0, ry=0.0, rz=rz), tz


def targetless_start(
    recording: Scan,
    platter: PlatterGeometry,
    settings: InitialSettings = InitialSettings(),
    *,
    prepared: SpinScan | None = None,
) -> CalibrationResult:
    """The initial calibration from the platter's chord in a spin scan (strategy ``platter``),
    with the line segmentation of the initial calibration (``settings``).

    tz is 0 here; the diagnostics give the chord, its |tz| and the candidates for the
    fine-tuning (``tz_candidates_m``). σ: rz from the chord's
    residuals, tx and ty from its ends (a bin's width), tz and ry not estimated. ``prepared``:
    the recording's returns already prepared (:func:`calstation.engine.spinscan.from_recording`).
    """
    from calstation.engine.result import CalibrationResult
    from calstation.engine.spinscan import from_recording

    t0 = time.perf_counter()
    scan = prepared if prepared is not None else from_recording(recording)
    all_az = recording.azimuth_rad
    if all_az.size == 0:
        raise InitialCalibrationError(f"{recording.path}: the spin scan has no returns")
    fov = (float(all_az.min()), float(all_az.max()))
    try:
        chord = find_platter_chord(scan.az, scan.rng, scan.static, platter, fov, settings)
    except InitialCalibrationError as exc:
        raise InitialCalibrationError(f"{recording.path}: {exc}") from None
    H, tz = extrinsics_from_chord(chord, platter.radius)
    candidates = [0.0, tz, -tz] if tz >= TZ_SIGN_MIN_M else [0.0]
    H = H.with_(tz=0.0)
    step = float(np.linalg.norm(chord.midpoint)) * math.radians(BIN_DEG)
    n = sum(s.n for s in chord.segments)
    sigma = {"tx": step, "ty": step, "tz": math.nan, "rx": math.nan, "ry": math.nan,
             "rz": chord.rms * math.sqrt(12.0 / max(n, 3)) / max(chord.length, 1e-3)}
    return CalibrationResult(
        H=H, sigma=sigma, cost=chord.rms**2, iterations=1, strategy="platter",
        timings={"total": time.perf_counter() - t0},
        diagnostics={
            "chord": chord.describe(),
            "chord_length_m": chord.length,
            "tz_from_chord_m": tz,
            "tz_candidates_m": candidates,
            "assumption": "ry = 0 (paper Assumption 1); rx = 0 (gauge); the sign of tz from "
                          "the fine-tuning",
        },
    )
