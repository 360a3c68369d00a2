"""The accuracy budget: how far a calibration's uncertainty can distort what the station scans.

A user of the station does not feel σ_ry or σ_tz; they feel how wrong the reconstructed object
is. An error δH of the calibration moves every return's reconstruction in frame D; the part of
that motion which is the same for every return — a rigid shift or turn of the whole object — is
no distortion (the object only sits elsewhere), so it is removed by the best rigid alignment,
as DESIGN §8 measures the true distortion. What remains is the distortion.

:func:`predicted_error` propagates the covariance of H to the points of a *work volume* (a
cylinder on the platter: the platter's radius and a height, the largest object the station is
meant for), each seen where it crosses the scan plane in both half-turns, as the station would
see an object filling it. It draws δH from the covariance, removes the rigid part, and takes the
largest displacement over the volume; the error at ``level`` (95 %) is that maximum's quantile.
A known bound on a remaining bias (per parameter) is added at its worst combination of signs.
The station's gate compares it with ``calibration.accuracy.max_error``.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from calstation.engine.frames import PARAMETER_NAMES, Extrinsics, FloatArray, lidar_to_dynamic
from calstation.engine.rangemodel import IDENTITY, RANGE_NAMES, RangeModel, unit_rays

if TYPE_CHECKING:
    from calstation.engine.periodicity.covariance import CovarianceRecord

RINGS = 24
"""Points around each circle of the work volume."""
LEVELS = 5
"""Heights of the work volume's circles, from the platter top to its height."""
SAMPLES = 4000
"""Draws of δH from its covariance."""
STEP = 1e-6
"""Central-difference step of the reconstruction's Jacobian (m or rad)."""


@dataclass(frozen=True)
class PredictedError:
    """The predicted distortion of an object filling the work volume.

    ``max_m``: the largest displacement over the volume, at ``level`` (metres); ``rms_m``: the
    RMS displacement over the volume at the same level; ``bias_m``: how much of ``max_m`` is the
    bias bound; ``points`` (N, 3): the volume's points in frame D; ``per_point_m`` (N,): each
    point's displacement at ``level`` (where in the volume the error is largest);
    ``parameters``: the parameters whose uncertainty was propagated.
    """

    max_m: float
    rms_m: float
    bias_m: float
    level: float
    points: FloatArray
    per_point_m: FloatArray
    parameters: tuple[str, ...]

    def as_dict(self) -> dict[str, object]:
        """The figures (metres), where the largest point is (frame D, metres), and the map of
        the volume: ``[x, y, z, error]`` per point (metres, to the micrometre)."""
        worst = int(np.argmax(self.per_point_m)) if self.per_point_m.size else 0
        volume = np.column_stack([self.points, self.per_point_m]) if self.points.size else None
        return {
            "max_m": self.max_m,
            "rms_m": self.rms_m,
            "bias_m": self.bias_m,
            "level": self.level,
            "parameters": list(self.parameters),
            "worst_point_m": self.points[worst].tolist() if self.points.size else None,
            "map": None if volume is None else np.round(volume, 6).tolist(),
        }


def work_volume(radius: float, height: float) -> FloatArray:
    """(N, 3) points in frame D filling a cylinder on the platter: circles of :data:`RINGS`
    points at radius, ⅔ and ⅓ of it, on :data:`LEVELS` heights from 0 to ``height``, and the
    axis."""
    theta = np.linspace(0.0, 2 * math.pi, RINGS, endpoint=False)
    pts = []
    for x in np.linspace(0.0, height, LEVELS):
        pts.append([x, 0.0, 0.0])
        for r in (radius, 2 * radius / 3, radius / 3):
            pts += [[x, r * math.cos(a), r * math.sin(a)] for a in theta]
    return np.asarray(pts, dtype=np.float64)


def sightings(
    points_D: FloatArray, H: Extrinsics
) -> tuple[NDArray[np.intp], FloatArray, FloatArray]:
    """Where the station sees each point: the platter angles at which it lies in the scan plane.

    A point turning with the platter crosses the plane z_L = 0 twice a turn (once on each side
    of the axis) unless its circle misses the plane. Returns, per sighting: the index of the
    point (M,), φ (M,), and the return in L (M, 3).
    """
    R, t = H.R, H.t
    x, y, z = points_D[:, 0], points_D[:, 1], points_D[:, 2]
    # z_L = x·R20 + (y·cosφ − z·sinφ)·R21 + (y·sinφ + z·cosφ)·R22 + tz = A·cosφ + B·sinφ − C
    A = y * R[2, 1] + z * R[2, 2]
    B = -z * R[2, 1] + y * R[2, 2]
    C = -(x * R[2, 0] + t[2])
    amp = np.hypot(A, B)
    ratio = np.full(points_D.shape[0], 2.0)
    np.divide(C, amp, out=ratio, where=amp > 1e-12)
    seen = np.flatnonzero(np.abs(ratio) <= 1.0)
    base = np.arctan2(B[seen], A[seen])
    spread = np.arccos(ratio[seen])
    index = np.concatenate([seen, seen])
    phi = np.concatenate([base + spread, base - spread])
    p_D = points_D[index]
    c, s = np.cos(phi), np.sin(phi)
    p_P = np.column_stack([p_D[:, 0], c * p_D[:, 1] - s * p_D[:, 2], s * p_D[:, 1] + c * p_D[:, 2]])
    return index, phi, p_P @ R.T + t


def displacement_jacobian(
    p_L: FloatArray, phi: FloatArray, H: Extrinsics, names: tuple[str, ...]
) -> FloatArray:
    """(M, 3, n) ∂p_D/∂H of the reconstruction ``p_D = Rx(φ)ᵀ·Rᵀ·(p_L − t)`` with respect to
    the parameters ``names`` (the returns ``p_L`` and their φ held: they are measured)."""
    out = np.empty((p_L.shape[0], 3, len(names)))
    for k, name in enumerate(names):
        if name in RANGE_NAMES:
            # the range terms move each return along its own ray (the lidar at the origin of
            # L): −ray per metre of offset, −p_L per unit of scale error
            along = unit_rays(p_L) if name == "range_offset" else p_L
            out[:, :, k] = -lidar_to_dynamic(along, phi, H.with_(tx=0.0, ty=0.0, tz=0.0))
            continue
        value = getattr(H, name)
        plus = lidar_to_dynamic(p_L, phi, H.with_(**{name: value + STEP}))
        minus = lidar_to_dynamic(p_L, phi, H.with_(**{name: value - STEP}))
        out[:, :, k] = (plus - minus) / (2 * STEP)
    return out


def _without_rigid(J: FloatArray, p_D: FloatArray) -> FloatArray:
    """(3M, n) the part of the displacements ``J`` (M, 3, n) that no rigid motion of the
    points ``p_D`` (M, 3) explains (the residual of their linearised best alignment)."""
    m = p_D.shape[0]
    c = p_D - p_D.mean(axis=0)
    rigid = np.zeros((m, 3, 6))
    # δp = ω × p + τ: ω × p = −[p]× ω
    rigid[:, 0, 1], rigid[:, 0, 2] = c[:, 2], -c[:, 1]
    rigid[:, 1, 0], rigid[:, 1, 2] = -c[:, 2], c[:, 0]
    rigid[:, 2, 0], rigid[:, 2, 1] = c[:, 1], -c[:, 0]
    rigid[:, :, 3:] = np.eye(3)
    A = rigid.reshape(3 * m, 6)
    Jf = J.reshape(3 * m, -1)
    coef, *_ = np.linalg.lstsq(A, Jf, rcond=None)
    residual: FloatArray = Jf - A @ coef
    return residual


def _covariance_of(
    covariance: CovarianceRecord | None, sigma: Mapping[str, float]
) -> tuple[tuple[str, ...], FloatArray]:
    """The parameters with an uncertainty and their covariance: the stored covariance record
    (``parameters``, ``matrix``) where there is one, else the σ alone (uncorrelated)."""
    if covariance is not None and covariance.get("parameters"):
        names = tuple(str(n) for n in covariance["parameters"])
        matrix = np.asarray(covariance["matrix"], dtype=np.float64)
        extra = [
            n for n in PARAMETER_NAMES
            if n not in (*names, "rx", "ty") and math.isfinite(sigma.get(n, math.nan))
        ]
        if extra:
            full = np.zeros((len(names) + len(extra),) * 2)
            full[: len(names), : len(names)] = matrix
            for k, n in enumerate(extra, start=len(names)):
                full[k, k] = sigma[n] ** 2
            return (*names, *extra), full
        return names, matrix
    names = tuple(
        n for n in PARAMETER_NAMES
        if n not in ("rx", "ty") and math.isfinite(sigma.get(n, math.nan))
    )
    return names, np.diag([sigma[n] ** 2 for n in names])


def predicted_error(
    H: Extrinsics,
    sigma: Mapping[str, float],
    covariance: CovarianceRecord | None = None,
    *,
    radius: float,
    height: float,
    level: float = 0.95,
    bias: Mapping[str, float] | None = None,
    samples: int = SAMPLES,
    seed: int = 0,
) -> PredictedError:
    """The distortion of an object filling the work volume (``radius``, ``height``, metres)
    that the uncertainty of ``H`` allows, at ``level``: see the module docstring.

    ``sigma``: 1σ per parameter (NaN: held, not propagated); ``covariance``: the stored record
    (``parameters`` and ``matrix``, SI) when the strategy gives one; ``bias``: a bound on the
    remaining bias per parameter (m or rad). The covariance's range terms (``range_offset``,
    ``range_scale``) move each return along its ray. ty is propagated when the covariance has
    it; its σ alone is not (without its correlations it would be the gauge along the axis).
    """
    names, cov = _covariance_of(covariance, sigma)
    points = work_volume(radius, height)
    index, phi, p_L = sightings(points, H)
    if index.size < 4 or not names:
        return PredictedError(math.nan, math.nan, 0.0, level, points, np.zeros(0), names)
    p_D = points[index]
    M = _without_rigid(displacement_jacobian(p_L, phi, H, names), p_D)  # (3M, n)
    w, v = np.linalg.eigh(0.5 * (cov + cov.T))
    root = v * np.sqrt(np.clip(w, 0.0, None))
    draws = root @ np.random.default_rng(seed).standard_normal((len(names), samples))
    # (M, S) each sighting's displacement per draw: its three components' squares summed in
    # order, as numpy.linalg.norm would, without its two temporaries of (3M, S)
    d = (M @ draws).reshape(index.size, 3, samples)
    disp = np.sqrt(d[:, 0] ** 2 + d[:, 1] ** 2 + d[:, 2] ** 2)
    bias_m = _bias_bound(M, names, bias, index.size)
    per_sighting = np.quantile(disp, level, axis=1)
    per_point = np.zeros(points.shape[0])
    np.maximum.at(per_point, index, per_sighting)
    seen = np.unique(index)
    return PredictedError(
        max_m=float(np.quantile(disp.max(axis=0), level)) + bias_m,
        rms_m=float(np.quantile(np.sqrt(np.mean(disp**2, axis=0)), level)),
        bias_m=bias_m,
        level=level,
        points=points[seen],
        per_point_m=per_point[seen],
        parameters=names,
    )


def axis_offset_sigma(H: Extrinsics, covariance: CovarianceRecord | None) -> float:
    """The σ of where the axis lies, across it at the platter centre (m): the RMS of the
    distance DESIGN §8 measures between the estimated and the true axis lines, from the
    covariance of (tx, ty, tz) — the platter centre is H's origin, so ry and rz only turn the
    line about it. NaN when the covariance does not hold all three (ty held: the gauge along the
    axis, which leaves the distance across it to tx and tz alone)."""
    if covariance is None:
        return math.nan
    names = list(covariance.get("parameters", []))
    if not all(n in names for n in ("tx", "ty", "tz")):
        return math.nan
    at = [names.index(n) for n in ("tx", "ty", "tz")]
    C = np.asarray(covariance["matrix"], dtype=np.float64)[np.ix_(at, at)]
    axis = H.axis_direction()
    across = np.eye(3) - np.outer(axis, axis)
    return float(math.sqrt(max(float(np.trace(across @ C @ across)), 0.0)))


def _bias_bound(
    M: FloatArray, names: tuple[str, ...], bias: Mapping[str, float] | None, m: int
) -> float:
    """The largest displacement over the volume that the bias bounds can cause, at their worst
    combination of signs (metres)."""
    if not bias:
        return 0.0
    b = np.array([abs(float(bias.get(n, 0.0))) for n in names])
    if not np.any(b > 0):
        return 0.0
    # every combination of signs at once: (3M, 2ⁿ) displacements
    signs = np.array(list(itertools.product((-1.0, 1.0), repeat=len(names))))
    d = (M @ (b * signs).T).reshape(m, 3, signs.shape[0])
    return float(np.sqrt(np.einsum("mik,mik->mk", d, d)).max())


def true_distortion(
    estimate: Extrinsics, truth: Extrinsics, *, radius: float, height: float,
    estimate_range: RangeModel = IDENTITY, truth_range: RangeModel = IDENTITY,
) -> dict[str, float]:
    """What the simulator knows: the work volume seen under the true H by a lidar of the true
    range model (``truth_range``: its offset and scale error), and reconstructed with
    ``estimate`` and the estimated range model; after the best rigid alignment, the largest and
    the RMS displacement (m)."""
    from calstation.engine.metrics import kabsch

    points = work_volume(radius, height)
    index, phi, p_L = sightings(points, truth)
    p_D = points[index]
    rho = np.linalg.norm(p_L, axis=1, keepdims=True)
    measured = p_L * (((1.0 + truth_range.scale) * rho + truth_range.offset) / rho)
    est = lidar_to_dynamic(estimate_range.points(measured), phi, estimate)
    R, t = kabsch(est, p_D)
    d = np.linalg.norm(est @ R.T + t - p_D, axis=1)
    return {"max_m": float(d.max()), "rms_m": float(np.sqrt(np.mean(d**2)))}


def data_factor(predicted: PredictedError, budget_m: float) -> float:
    """How many times more data (returns of the same kind) would bring ``predicted`` within
    ``budget_m``: the random part of the error falls as 1/√data, a bias bound does not.
    1 when it is within already; ``inf`` when the bias bound alone exceeds the budget."""
    if predicted.max_m <= budget_m:
        return 1.0
    random = predicted.max_m - predicted.bias_m
    room = budget_m - predicted.bias_m
    if room <= 0 or random <= 0:
        return math.inf
    return (random / room) ** 2


def contributions(
    H: Extrinsics,
    sigma: Mapping[str, float],
    covariance: CovarianceRecord | None,
    *,
    radius: float,
    height: float,
    level: float = 0.95,
) -> dict[str, float]:
    """The predicted error (m) each parameter's uncertainty would cause alone: which one
    limits the accuracy, and so what would help (a taller target for ry, …)."""
    names, cov = _covariance_of(covariance, sigma)
    out = {}
    for k, name in enumerate(names):
        alone = {n: (math.sqrt(max(cov[k, k], 0.0)) if n == name else math.nan) for n in names}
        out[name] = predicted_error(
            H, alone, radius=radius, height=height, level=level, samples=1000
        ).max_m
    return out
