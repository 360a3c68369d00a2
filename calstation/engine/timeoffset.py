"""The lidar–encoder time offset, from two passes of the spin scan at different platter speeds.

Each point's platter angle comes from the encoder, interpolated at the point's time. If the
encoder's clock runs Δ behind what the station's configured latency assumes, every angle is late
by ω·Δ (ω the platter speed), and the reconstruction in D turns by ω·Δ about the axis. At one
constant speed that turn is a free gauge (rx) and does no harm; at another speed, or turning the
other way, the same Δ turns the cloud by a different angle, so objects scanned at two speeds (or
merged from both directions) no longer fit together.

The estimate uses exactly that. Both passes see the same fixture, and any point of it is seen at
the same platter angle whatever the speed, so an error in H distorts the two reconstructions in
the same way; what differs between them is only the turn ``θ = (ω₁ − ω₂)·Δ``. The second pass's
moving returns are aligned to the first's by a rotation about X_D alone (point-to-plane, after a
coarse search), and ``Δ = θ / (ω₁ − ω₂)``. Its σ comes from the spread of independent
estimates on groups of sectors of the turn, so that errors that change along the turn (range
noise on a few faces, speed ripple) show in it.

The result is the encoder latency to use (encoder time minus lidar time, s): the recordings'
configured latency plus Δ.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from calstation.engine.frames import Extrinsics, FloatArray
from calstation.engine.rangemodel import IDENTITY, RangeModel
from calstation.errors import FineTuningError

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

    from calstation.engine.result import CalibrationResult
    from calstation.engine.scan import Scan
    from calstation.engine.spinscan import SpinScan

SEARCH_S = 0.1
"""The coarse search covers offsets of ± this many seconds."""

MARGIN = 0.01
"""Returns this far above the platter top (m) belong to the fixture."""

VOXEL = 0.003
"""The first pass's returns are averaged in cubes of this edge (m) before the second is aligned
to them: the mean of a cube's returns sits on the surface with far less noise, and the averaged
cloud has the same density in every direction (a spin scan is much denser along the turn than
along a line), which its normals need to be unbiased."""

MAX_TURNED = 200_000
"""Returns of the second pass aligned (an even subset)."""

NORMAL_K = 16
SECTORS = 12
"""Sectors of the turn (about the axis, in D); sectors k and k + 6 make one of the six groups
whose independent estimates give the σ."""
SECTOR_MARGIN = 0.05
"""The fixed pass keeps this much (rad) of the neighbouring sectors in a group's estimate, so
that the turned pass's returns at a sector's edge still find their surface."""

MAX_ITERATIONS = 20
STEP_TOL = 2e-6
"""Gauss–Newton stops when the turn changes by less than this (rad): a few µs of offset at the
smallest speed difference a recipe allows, far below the noise. (Near the solution the trimmed
pairs change from one iteration to the next, and the turn cycles within about 1e-6 rad.)"""

MIN_PAIRS = 2_000
MIN_GROUPS = 3
"""Groups of sectors that must give an estimate of their own for the σ to be measured."""
MIN_SPEED_RATIO = 0.5
"""The passes' speeds must differ by this fraction of the faster one (as the recipe checks)."""


@dataclass(frozen=True)
class TimeOffset:
    """The estimated lidar–encoder time offset.

    ``latency_s`` is the encoder latency to use from now on (encoder time minus lidar time, s),
    ``sigma_s`` its 1σ; ``configured_s`` what the recordings assumed, so ``latency_s −
    configured_s`` is the correction. ``rotation_rad`` is the turn that aligned the second pass
    to the first, ``speeds_rad_s`` the passes' mean signed speeds, ``pairs`` the point pairs of
    the final fit, ``groups_aligned`` how many of the :data:`SECTORS` / 2 groups of sectors gave
    an estimate of their own for the σ (in the weaker of the two directions; fewer than
    :data:`MIN_GROUPS` leave the σ infinite).
    """

    latency_s: float
    sigma_s: float
    configured_s: float
    rotation_rad: float
    speeds_rad_s: tuple[float, float]
    pairs: int
    groups_aligned: int
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def correction_s(self) -> float:
        """How much the configured latency was off (s)."""
        return self.latency_s - self.configured_s

    def as_dict(self) -> dict[str, object]:
        """Plain mapping (seconds and radians) for diagnostics and reports."""
        return {
            "latency_s": self.latency_s,
            "sigma_s": self.sigma_s,
            "configured_s": self.configured_s,
            "correction_s": self.correction_s,
            "rotation_rad": self.rotation_rad,
            "speeds_rad_s": list(self.speeds_rad_s),
            "pairs": self.pairs,
            "groups_aligned": self.groups_aligned,
            "groups": SECTORS // 2,
            "groups_needed": MIN_GROUPS,
            "timings": dict(self.timings),
        }


def mean_speed(recording: Scan) -> float:
    """The platter's mean signed speed (rad/s) over the recording's lines."""
    t = recording.line_timestamp_ns
    if t.size < 2:
        raise FineTuningError(f"{recording.path}: too few lidar lines to measure the speed")
    phi = recording.platter_angle(np.array([t[0], t[-1]], dtype=np.int64))
    if not np.all(np.isfinite(phi)):
        raise FineTuningError(f"{recording.path}: the encoder does not cover the lidar lines")
    return float((phi[1] - phi[0]) / ((t[-1] - t[0]) * 1e-9))


def fixture_cloud(
    recording: Scan, H: Extrinsics, platter_radius: float, prepared: SpinScan | None = None,
    range_model: RangeModel = IDENTITY,
) -> FloatArray:
    """The moving returns above the platter, in D under ``H`` and the lidar's ``range_model``:
    (N, 3) points (``prepared``: the recording's returns already prepared)."""
    from calstation.engine.geometry import segment_above_platter
    from calstation.engine.reconstruct import lidar_points_to_dynamic
    from calstation.engine.spinscan import from_recording

    scan = prepared if prepared is not None else from_recording(recording)
    p_D = lidar_points_to_dynamic(range_model.points(scan.p_L), scan.phi, H)
    keep = ~scan.static & segment_above_platter(
        p_D, margin=MARGIN, radius=platter_radius, height=math.inf
    )
    out: FloatArray = p_D[keep]
    return out


def _every(n: int, cap: int) -> slice:
    return slice(None, None, max(1, math.ceil(n / cap)))


def voxel_means(p: FloatArray, voxel: float) -> FloatArray:
    """The mean of the (N, 3) points in each occupied cube of edge ``voxel`` (m)."""
    if p.shape[0] == 0:
        return p
    key = np.floor(p / voxel).astype(np.int64)
    key -= key.min(axis=0)
    span = key.max(axis=0) + 1
    flat = (key[:, 0] * span[1] + key[:, 1]) * span[2] + key[:, 2]
    _, inverse, counts = np.unique(flat, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    sums = np.column_stack([np.bincount(inverse, weights=p[:, a]) for a in range(3)])
    out: FloatArray = sums / counts[:, None]
    return out


def _turn(p: FloatArray, theta: float) -> FloatArray:
    """Points turned by ``theta`` about +X (right-handed)."""
    c, s = math.cos(theta), math.sin(theta)
    out = p.copy()
    out[:, 1] = c * p[:, 1] - s * p[:, 2]
    out[:, 2] = s * p[:, 1] + c * p[:, 2]
    return out


def _coarse(tree: cKDTree, moving: FloatArray, limit: float) -> float:
    """The turn in ±``limit`` (rad) with the smallest median distance, on a grid then finer."""
    sample = moving[_every(moving.shape[0], 5_000)]
    centre, half, steps = 0.0, limit, 121
    for _ in range(3):
        grid = np.linspace(centre - half, centre + half, steps)
        cost = [float(np.median(tree.query(_turn(sample, th), workers=-1)[0])) for th in grid]
        best = int(np.argmin(cost))
        centre, half, steps = float(grid[best]), 2.0 * (grid[1] - grid[0]), 41
    return centre


def _fit(
    fixed: FloatArray, normals: FloatArray, weights: FloatArray, tree: cKDTree,
    moving: FloatArray, theta: float, max_distance: float,
) -> tuple[float, NDArray[np.intp], FloatArray, FloatArray]:
    """Point-to-plane Gauss–Newton on the turn alone, from ``theta``; returns the turn, the
    moving points paired in the last iteration, their Jacobian and residuals (both scaled by
    the square root of the pair's planarity weight)."""
    ex_cross = np.zeros_like(moving)
    used = np.zeros(0, dtype=np.intp)
    J = r = np.zeros(0)
    for _ in range(MAX_ITERATIONS):
        turned = _turn(moving, theta)
        d, j = tree.query(turned, distance_upper_bound=max_distance, workers=-1)
        ok = np.flatnonzero(np.isfinite(d))
        j = j[ok]
        n = normals[j]
        r = np.einsum("ij,ij->i", n, turned[ok] - fixed[j])
        # d/dθ of the turned point is e_x × p = (0, −p_z, p_y)
        ex_cross = np.column_stack([np.zeros(ok.size), -turned[ok, 2], turned[ok, 1]])
        J = np.einsum("ij,ij->i", n, ex_cross)
        mad = 1.4826 * float(np.median(np.abs(r))) if r.size else 0.0
        good = (np.abs(r) <= 3.0 * max(mad, 1e-5)) & (weights[j] > 0.5)
        used, J, r = ok[good], J[good], r[good]
        if used.size < MIN_PAIRS:
            raise FineTuningError(
                f"time offset: only {used.size} point pairs between the two passes (at least "
                f"{MIN_PAIRS} are needed): is the same fixture on the platter in both passes?"
            )
        root_w = np.sqrt(weights[j[good]])
        J, r = J * root_w, r * root_w
        step = -float(np.sum(J * r) / np.sum(J * J))
        theta += step
        if abs(step) < STEP_TOL:
            break
    return theta, used, J, r


def _sectors(p: FloatArray, widen: float = 0.0) -> list[NDArray[np.intp]]:
    """Each point's sector of the turn (where it sits about the axis), :data:`SECTORS` in all;
    with ``widen`` (rad), also the sectors within that angle either side."""
    around = np.arctan2(p[:, 2], p[:, 1]) + math.pi
    width = 2 * math.pi / SECTORS
    return [np.floor(np.mod(around + d, 2 * math.pi) / width).astype(np.intp) % SECTORS
            for d in ((0.0,) if widen == 0.0 else (-widen, 0.0, widen))]


def _group_sigma(fixed: FloatArray, turned: FloatArray, theta: float) -> tuple[float, int]:
    """1σ of the turn from independent estimates on the :data:`SECTORS` / 2 groups of sectors of
    the turn in both passes (sectors k and k + SECTORS/2 form a group): their information-weighted
    spread, which holds every error that differs across the turn, in either pass; and how many
    groups gave an estimate (the σ is infinite with fewer than :data:`MIN_GROUPS`)."""
    groups = SECTORS // 2
    in_a = [s % groups for s in _sectors(fixed, SECTOR_MARGIN)]
    (in_b,) = [s % groups for s in _sectors(turned)]
    est, info = [], []
    for g in range(groups):
        a = fixed[np.logical_or.reduce([s == g for s in in_a])]
        b = turned[in_b == g]
        if min(a.shape[0], b.shape[0]) < MIN_PAIRS:
            continue
        try:
            theta_g, _, J, _ = _fit_to(a, b, theta, VOXEL)
        except FineTuningError:
            continue
        est.append(theta_g)
        info.append(float(np.sum(J * J)))
    if len(est) < MIN_GROUPS:
        return math.inf, len(est)
    th, w = np.array(est), np.array(info)
    mean = float(np.sum(w * th) / np.sum(w))
    sigma = math.sqrt(np.sum(w * (th - mean) ** 2) / ((len(est) - 1) * np.sum(w)))
    return float(sigma), len(est)


def _fit_to(
    fixed: FloatArray, turned: FloatArray, theta: float, max_distance: float
) -> tuple[float, NDArray[np.intp], FloatArray, FloatArray]:
    """:func:`_fit` of the measured ``turned`` onto ``fixed`` averaged in cubes, from ``theta``."""
    from calstation.engine.neighbours import tree, weighted_normals

    a = voxel_means(fixed, VOXEL)
    t_a = tree(a)
    normals, weights, _ = weighted_normals(a, NORMAL_K, t=t_a)
    return _fit(a, normals, weights, t_a, turned, theta, max_distance)


def _align(
    fixed: FloatArray, turned: FloatArray, limit: float
) -> tuple[float, float, int, int]:
    """The turn about X_D (rad) that puts ``turned`` onto ``fixed``, its 1σ, the pairs used and
    the groups of sectors that gave the σ.

    ``fixed`` is averaged in cubes of :data:`VOXEL` and given normals; ``turned`` stays as
    measured (averaged on the same grid its cubes would lock onto ``fixed``'s at no turn). A
    coarse search within ±``limit`` rad, then point-to-plane Gauss–Newton; the σ from
    independent estimates on groups of sectors (:func:`_group_sigma`).
    """
    from calstation.engine.neighbours import tree, weighted_normals

    b = turned[_every(turned.shape[0], MAX_TURNED)]
    a = voxel_means(fixed, VOXEL)
    if a.shape[0] < MIN_PAIRS or b.shape[0] < MIN_PAIRS:
        raise FineTuningError(
            f"time offset: the passes show {fixed.shape[0]} and {turned.shape[0]} returns of "
            f"the fixture above the platter; too few to align them (is the fixture on the "
            "platter in both passes?)"
        )
    t_a = tree(a)
    normals, weights, _ = weighted_normals(a, NORMAL_K, t=t_a)
    theta = _coarse(t_a, b, limit)
    if abs(theta) > 0.98 * limit:
        raise FineTuningError(
            f"time offset: the passes align best at the edge of the search (±{SEARCH_S * 1e3:g} "
            "ms): the offset is larger than that, or the passes do not show the same fixture"
        )
    # the wide first fit only brings the turn close: a quarter of the returns do
    theta, _, _, _ = _fit(a, normals, weights, t_a, b[::4], theta, 2.0 * VOXEL)
    theta, used, _, _ = _fit(a, normals, weights, t_a, b, theta, VOXEL)
    sigma, groups = _group_sigma(fixed, b, theta)
    return theta, sigma, int(used.size), groups


def estimate_time_offset(
    first: Scan,
    second: Scan,
    H: Extrinsics,
    platter_radius: float,
    progress: Callable[[str, float], None] | None = None,
    *,
    prepared_first: SpinScan | None = None,
    range_model: RangeModel = IDENTITY,
) -> TimeOffset:
    """The lidar–encoder time offset from two passes of the spin scan under the calibration H
    (and the lidar's ``range_model``).

    ``first`` and ``second`` are the two passes' recordings (the same fixture, different signed
    speeds, the same configured encoder latency); ``prepared_first`` the first pass's returns
    already prepared. Raises :class:`FineTuningError` when they
    cannot give it: speeds too alike, too little of the fixture in common, or an offset beyond
    ± :data:`SEARCH_S`.
    """
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    if first.encoder_latency_s != second.encoder_latency_s:
        raise FineTuningError(
            f"time offset: the two passes assume different encoder latencies "
            f"({first.encoder_latency_s:g} s in {first.path}, {second.encoder_latency_s:g} s in "
            f"{second.path}); take both with the same station configuration"
        )
    w1, w2 = mean_speed(first), mean_speed(second)
    contrast = w1 - w2
    if abs(contrast) < MIN_SPEED_RATIO * max(abs(w1), abs(w2)):
        raise FineTuningError(
            f"time offset: the passes turn at {w1 * 30 / math.pi:.3g} and "
            f"{w2 * 30 / math.pi:.3g} rpm, too alike to show the offset; turn the second pass "
            "the other way (steps.spin_scan.second_pass_rpm)"
        )
    if progress is not None:
        progress("time offset: reconstructing both passes", 0.0)
    clouds = [fixture_cloud(first, H, platter_radius, prepared_first, range_model),
              fixture_cloud(second, H, platter_radius, range_model=range_model)]
    timings["clouds"] = time.perf_counter() - t0
    if progress is not None:
        progress("time offset: aligning the passes", 0.3)
    # each pass aligned to the other, and the two turns averaged: what one direction of the
    # fit gets wrong (a cube's mean is not a measured point) the other gets wrong the other way
    t1 = time.perf_counter()
    forward = _align(clouds[0], clouds[1], abs(contrast) * SEARCH_S)
    if progress is not None:
        progress("time offset: aligning the passes", 0.65)
    backward = _align(clouds[1], clouds[0], abs(contrast) * SEARCH_S)
    timings["align"] = time.perf_counter() - t1
    theta = 0.5 * (forward[0] - backward[0])
    sigma_theta = 0.5 * (forward[1] + backward[1])  # the two fits share the data: no √2
    pairs = min(forward[2], backward[2])
    if progress is not None:
        progress("time offset: done", 1.0)
    delta = theta / contrast
    return TimeOffset(
        latency_s=first.encoder_latency_s + delta,
        sigma_s=sigma_theta / abs(contrast),
        configured_s=first.encoder_latency_s,
        rotation_rad=theta,
        speeds_rad_s=(w1, w2),
        pairs=pairs,
        groups_aligned=min(forward[3], backward[3]),
        timings=timings,
    )


def with_time_offset(
    result: CalibrationResult,
    first: Scan,
    second: Scan,
    platter_radius: float,
    progress: Callable[[str, float], None] | None = None,
    *,
    prepared_first: SpinScan | None = None,
) -> CalibrationResult:
    """``result`` with the time offset estimated from the spin scan's two passes under its H:
    ``encoder_latency_s``, its σ, and the estimate's details in ``diagnostics["time_offset"]``
    (``prepared_first``: the first pass's returns already prepared)."""
    offset = estimate_time_offset(first, second, result.H, platter_radius, progress,
                                  prepared_first=prepared_first, range_model=result.range_model)
    diagnostics = {**result.diagnostics, "time_offset": offset.as_dict()}
    timings = {**result.timings, "time_offset": sum(offset.timings.values())}
    return replace(
        result,
        encoder_latency_s=offset.latency_s,
        sigma_encoder_latency_s=offset.sigma_s,
        diagnostics=diagnostics,
        timings=timings,
    )
