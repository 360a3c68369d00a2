"""Initial calibration from a static scan of the L-target (paper §III-A, §IV-A; DESIGN §3, §5).

1. Azimuth-bin smoothing: median range per 0.02° bin over all lines of the static scan.
2. Contiguous straight segments by PCA split-and-merge.
3. Candidate pair: two consecutive segments meeting at ~90° in an inner corner, the base A′B′
   about ``base_length`` long, the wall B′C′ between ``h_short`` and ``h_tall``.
4. Eqs. 1–3 with the plate thicknesses: rz from the direction of A′B′; the corner B′ (the
   intersection of the two fitted lines) is B = (base_thickness, offset_y, ·) in P, so
   (tx, ty) = B′ − Rz(rz)·(base_thickness, offset_y); tz from the wall height seen:
   ``tz = w·(|B′C′| − h_mid)/(h_tall − h_short) − offset_z``. ry = 0 (Assumption 1), rx = 0.

Every failure raises :class:`InitialCalibrationError` saying what was seen and what was expected.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from calstation.engine.binning import BinnedScan, azimuth_bin_median
from calstation.engine.frames import Extrinsics, FloatArray
from calstation.engine.lines import Segment, intersect_lines, segment_profile
from calstation.engine.result import CalibrationResult
from calstation.engine.settings import InitialSettings, LTargetGeometry
from calstation.errors import CalibrationError, InitialCalibrationError

if TYPE_CHECKING:
    from calstation.engine.scan import Scan

MIN_BINS = 20
"""A static scan with fewer smoothed bins than this is treated as empty."""


@dataclass(frozen=True)
class LTargetFit:
    """The L-target found in a smoothed scan (scan plane, metres).

    ``a``, ``b``, ``c``: the points A′, B′ (corner), C′ (2,); ``base`` and ``wall`` the
    segments; ``corner_angle_deg`` the angle between them; ``score`` the relative misfit to the
    recipe's dimensions (smaller is better).
    """

    a: FloatArray
    b: FloatArray
    c: FloatArray
    base: Segment
    wall: Segment
    corner_angle_deg: float
    score: float

    @property
    def base_length(self) -> float:
        """|A′B′| in metres."""
        return float(np.linalg.norm(self.b - self.a))

    @property
    def wall_height(self) -> float:
        """|B′C′| in metres."""
        return float(np.linalg.norm(self.c - self.b))


def _expected(target: LTargetGeometry, tol: float) -> str:
    return (
        f"expected two consecutive segments meeting at 90° in an inner corner: a base "
        f"A′B′ of {target.base_length * 1e3:.0f} mm (±{tol * 100:.0f}%) and a wall B′C′ between "
        f"{target.h_short * 1e3:.0f} and {target.h_tall * 1e3:.0f} mm (±{tol * 100:.0f}%)"
    )


def _seen(segments: list[Segment]) -> str:
    if not segments:
        return "no straight segments"
    lines = [f"  #{i}: {s.describe()}" for i, s in enumerate(segments)]
    return f"{len(segments)} segments:\n" + "\n".join(lines)


def _pair_fit(
    s1: Segment, s2: Segment, target: LTargetGeometry, settings: InitialSettings
) -> tuple[LTargetFit | None, str]:
    """Try both assignments of (base, wall) to a consecutive pair; (fit or None, why not)."""
    cosang = abs(float(np.dot(s1.direction, s2.direction)))
    angle = math.degrees(math.acos(min(1.0, cosang)))
    if abs(angle - 90.0) > settings.angle_tolerance_deg:
        return None, f"corner angle {angle:.1f}° is not 90°±{settings.angle_tolerance_deg:g}°"
    try:
        corner = intersect_lines(s1.centroid, s1.direction, s2.centroid, s2.direction)
    except CalibrationError:
        return None, "the segments are parallel"
    gap = min(float(np.linalg.norm(corner - e)) for e in (s1.p0, s1.p1)) + min(
        float(np.linalg.norm(corner - e)) for e in (s2.p0, s2.p1)
    )
    max_gap = 0.1 * target.base_length + 0.01
    if gap > max_gap:
        return None, f"the segments do not meet (corner {gap * 1e3:.0f} mm from their ends)"
    tol = settings.length_tolerance
    best: LTargetFit | None = None
    why = ""
    for base, wall in ((s1, s2), (s2, s1)):
        a = max((base.p0, base.p1), key=lambda e: float(np.linalg.norm(e - corner)))
        c = max((wall.p0, wall.p1), key=lambda e: float(np.linalg.norm(e - corner)))
        # the wall's top edge lies between its last return and the next: add half a step
        c = c + 0.5 * (wall.length / max(wall.n - 1, 1)) * (c - corner) / max(
            float(np.linalg.norm(c - corner)), 1e-12
        )
        ab, bc = corner - a, c - corner
        la, lw = float(np.linalg.norm(ab)), float(np.linalg.norm(bc))
        if la == 0 or lw == 0:
            continue
        cross = float(ab[0] * bc[1] - ab[1] * bc[0]) / (la * lw)
        if cross > -0.5:
            why = why or "the corner is not an L opening toward the lidar (wrong handedness)"
            continue
        if abs(la - target.base_length) > tol * target.base_length:
            why = (
                f"base {la * 1e3:.1f} mm does not match {target.base_length * 1e3:.0f} mm"
                f" (wall {lw * 1e3:.1f} mm)"
            )
            continue
        if not (1 - tol) * target.h_short <= lw <= (1 + tol) * target.h_tall:
            why = (
                f"wall {lw * 1e3:.1f} mm is outside {target.h_short * 1e3:.0f}–"
                f"{target.h_tall * 1e3:.0f} mm (base {la * 1e3:.1f} mm)"
            )
            continue
        score = abs(la - target.base_length) / target.base_length + abs(angle - 90.0) / 90.0
        fit = LTargetFit(a, corner, c, base, wall, angle, score)
        if best is None or fit.score < best.score:
            best = fit
    return best, why


def find_l_target(
    segments: list[Segment], target: LTargetGeometry, settings: InitialSettings
) -> LTargetFit:
    """The consecutive segment pair that best fits the L-target; raises with what was seen."""
    if len(segments) < 2:
        raise InitialCalibrationError(
            f"L-target not found in the static scan: saw {_seen(segments)}; "
            f"{_expected(target, settings.length_tolerance)}"
        )
    best: LTargetFit | None = None
    reasons: list[str] = []
    for i in range(len(segments) - 1):
        fit, why = _pair_fit(segments[i], segments[i + 1], target, settings)
        if fit is None:
            reasons.append(f"  #{i}–#{i + 1}: {why}")
        elif best is None or fit.score < best.score:
            best = fit
    if best is None:
        raise InitialCalibrationError(
            "L-target not found in the static scan (absent, misplaced, occluded, or the recipe's "
            f"geometry is wrong): saw {_seen(segments)}\nconsecutive pairs:\n"
            + "\n".join(reasons)
            + f"\n{_expected(target, settings.length_tolerance)}"
        )
    return best


def extrinsics_from_fit(fit: LTargetFit, target: LTargetGeometry) -> Extrinsics:
    """Eqs. 1–3 with the thickness corrections; ry = rx = 0 (Assumption 1)."""
    d = fit.b - fit.a
    rz = -math.atan2(float(d[0]), float(d[1]))  # Eq. 1 (atan2 form)
    off_y, off_z = target.offset
    c, s = math.cos(rz), math.sin(rz)
    # B = (base_thickness, off_y, z) in P; its image in the scan plane is B′ (Eq. 2 corrected)
    bx = c * target.base_thickness - s * off_y
    by = s * target.base_thickness + c * off_y
    tx = float(fit.b[0]) - bx
    ty = float(fit.b[1]) - by
    tz = target.width * (fit.wall_height - target.h_mid) / (target.h_tall - target.h_short)
    tz -= off_z  # Eq. 3 relative to the target's centre line
    return Extrinsics(tx=tx, ty=ty, tz=tz, rx=0.0, ry=0.0, rz=rz)


def initial_from_returns(
    azimuth_rad: ArrayLike,
    range_m: ArrayLike,
    valid: ArrayLike | None,
    target: LTargetGeometry,
    settings: InitialSettings = InitialSettings(),
) -> CalibrationResult:
    """Initial calibration from raw returns of a static scan ((M,) azimuth rad, range m, valid).

    Returns a :class:`CalibrationResult` with strategy ``"initial"``; sigma is a rough 1σ from
    the fit residuals for tx, ty, tz, rz and NaN for ry (not estimated).
    """
    t0 = time.perf_counter()
    binned = azimuth_bin_median(azimuth_rad, range_m, valid, bin_deg=settings.bin_deg)
    t1 = time.perf_counter()
    if len(binned) < MIN_BINS:
        raise InitialCalibrationError(
            f"the static scan is empty: {len(binned)} azimuth bins with valid returns "
            f"(need at least {MIN_BINS}); expected the L-target in front of the lidar"
        )
    pts = binned.points()
    spacing = float(np.median(np.linalg.norm(np.diff(pts, axis=0), axis=1)))
    segments = segment_profile(
        pts,
        tolerance=settings.line_tolerance,
        min_points=settings.min_segment_points,
        max_gap=max(0.01, 8.0 * spacing),
    )
    t2 = time.perf_counter()
    fit = find_l_target(segments, target, settings)
    H = extrinsics_from_fit(fit, target)
    t3 = time.perf_counter()
    return CalibrationResult(
        H=H,
        sigma=_sigma(fit, binned, target),
        cost=float(fit.base.rms**2 + fit.wall.rms**2),
        iterations=1,
        strategy="initial",
        timings={"binning": t1 - t0, "segments": t2 - t1, "fit": t3 - t2, "total": t3 - t0},
        diagnostics={
            "bins": len(binned),
            "segments": [s.describe() for s in segments],
            "A": fit.a.tolist(),
            "B": fit.b.tolist(),
            "C": fit.c.tolist(),
            "base_length_m": fit.base_length,
            "wall_height_m": fit.wall_height,
            "corner_angle_deg": fit.corner_angle_deg,
            "assumption": "ry = 0 (paper Assumption 1); rx = 0 (gauge)",
        },
    )


def _sigma(fit: LTargetFit, binned: BinnedScan, target: LTargetGeometry) -> dict[str, float]:
    """Rough 1σ from line residuals and the bin spacing (the wall top is found to ~1 bin)."""
    n_b = max(fit.base.n, 3)
    l_b = max(fit.base.length, 1e-3)
    s_rz = fit.base.rms * math.sqrt(12.0 / n_b) / l_b
    s_corner = math.hypot(fit.base.rms, fit.wall.rms) / math.sqrt(min(n_b, fit.wall.n))
    step = float(np.mean(binned.range_m)) * binned.bin_rad * 4.0
    s_tz = target.width / (target.h_tall - target.h_short) * math.hypot(step, s_corner)
    return {
        "tx": s_corner,
        "ty": s_corner,
        "tz": s_tz,
        "rx": math.nan,
        "ry": math.nan,
        "rz": s_rz,
    }


def initial_calibration(
    recording: Scan,
    target: LTargetGeometry,
    settings: InitialSettings = InitialSettings(),
) -> CalibrationResult:
    """Initial calibration from a static-scan
    :class:`~calstation.engine.scan.Scan`."""
    if recording.azimuth_rad.size == 0:
        raise InitialCalibrationError(
            f"{recording.path}: the static scan has no returns; expected ~100 lines of the L-target"
        )
    try:
        return initial_from_returns(
            recording.azimuth_rad, recording.range_m, recording.valid, target, settings
        )
    except InitialCalibrationError as exc:
        raise InitialCalibrationError(f"{recording.path}: {exc}") from None
