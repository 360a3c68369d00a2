"""The observability gate: refuse a calibration whose σ says the data do not determine it.

A fine-tuning always returns numbers; whether they mean anything depends on what the scan could
see. Each strategy reports a 1σ per parameter (docs/algorithms.md says how it is obtained);
:func:`check_sigma` compares them with the recipe's ``calibration.max_sigma`` and raises
:class:`~calstation.errors.ObservabilityError`, naming each parameter, its σ and its limit and
saying what to do, rather than hand the operator a silent guess.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from calstation.engine.result import CalibrationResult
from calstation.engine.settings import AccuracySettings, PlatterGeometry, SigmaLimits
from calstation.errors import ObservabilityError

if TYPE_CHECKING:
    from calstation.engine.accuracy import PredictedError
    from calstation.engine.periodicity.covariance import CovarianceRecord

ADVICE = {
    "spin_target": (
        "Re-place the spin target off-centre (about 60 mm from the axis) so that its facets "
        "face along the platter's turn as well as toward the axis, check that the lidar sees "
        "it in both half-turns, and retry; a noisier sensor needs more revolutions or a "
        "larger target."
    ),
    "qa_cube": (
        "Re-seat the QA cube so that the lidar sees at least two of its side faces over the "
        "turn, scan more turns (steps.cube_scan.revolutions), and retry. With a range noise "
        "near 1 mm the shape strategy rarely reaches the default limits (docs/algorithms.md, "
        "shape sweep): the periodicity strategy on the spin target does."
    ),
}


def sigma_problems(
    result: CalibrationResult, limits: SigmaLimits, skip: tuple[str, ...] = ()
) -> list[str]:
    """One message per parameter whose σ exceeds its limit, or cannot be computed; parameters
    in ``skip`` are left to a later check (ry, when the cube scan will add to it)."""
    checks = (
        ("tx", limits.tx, 1e3, "mm"),
        ("tz", limits.tz, 1e3, "mm"),
        ("ry", None if limits.ry_deg is None else math.radians(limits.ry_deg), math.degrees(1.0),
         "°"),
        ("rz", None if limits.rz_deg is None else math.radians(limits.rz_deg), math.degrees(1.0),
         "°"),
    )
    problems = []
    sigmas = result.sigma
    if all(not math.isfinite(sigmas.get(n, math.nan)) for n, *_ in checks):
        return ["no parameter has a σ: the data do not determine the calibration"]
    for name, limit, scale, unit in checks:
        if name in skip:
            continue
        sigma = sigmas.get(name, math.nan)
        if not math.isfinite(sigma):
            continue  # held by the strategy (its start is kept)
        if limit is not None and sigma > limit:
            field = f"{name}_deg" if unit == "°" else name
            problems.append(
                f"{name}: σ {sigma * scale:.3f} {unit} > {limit * scale:.3f} {unit} "
                f"(calibration.max_sigma.{field})"
            )
    problem = _time_offset_problem(result, limits)
    return problems if problem is None else [*problems, problem]


def _time_offset_problem(result: CalibrationResult, limits: SigmaLimits) -> str | None:
    """Why the estimated lidar–encoder time offset is refused, or None."""
    latency = result.sigma_encoder_latency_s
    if result.encoder_latency_s is None or (
        latency is not None and latency <= limits.encoder_latency_ms * 1e-3
    ):
        return None
    # from the estimate's details, not the σ's value: a stored σ that was infinite reads None
    details = result.diagnostics.get("time_offset") or {}
    aligned, needed = details.get("groups_aligned"), details.get("groups_needed")
    if aligned is not None and needed is not None and aligned < needed:
        return (
            f"lidar–encoder time offset: its σ could not be measured: only {aligned} of the "
            f"{details['groups']} groups of sectors of the turn could be aligned on their own "
            f"(at least {needed} are needed), so the two passes' "
            "returns of the spin target are too few or too noisy for the estimate. Scan both "
            "passes over more turns (steps.spin_scan.revolutions), so that more returns fall on "
            "the target; or "
            "leave out steps.spin_scan.second_pass_rpm and set station.encoder.latency_s from a "
            "measurement made elsewhere"
        )
    shown = "unknown" if latency is None else f"{latency * 1e3:.3f} ms"
    return (
        f"lidar–encoder time offset: σ {shown} > {limits.encoder_latency_ms:.3f} ms "
        "(calibration.max_sigma.encoder_latency_ms): turn the second pass the other way or "
        "faster, so that the two passes differ more in speed"
    )


def problems_with_cube(
    result: CalibrationResult, limits: SigmaLimits, ry_failure: str | None
) -> list[str]:
    """:func:`sigma_problems` of a result whose ry went through the cube step
    (:func:`calstation.pipeline.stages.with_cube`): that step's
    ``ry_failure``, when it has one, stands for ry."""
    if ry_failure is None:
        return sigma_problems(result, limits)
    return [*sigma_problems(result, limits, ("ry",)), ry_failure]


def check_sigma(
    result: CalibrationResult, limits: SigmaLimits, fixture: str, skip: tuple[str, ...] = ()
) -> None:
    """Raise :class:`ObservabilityError` when a σ of ``result`` exceeds ``limits``.

    ``fixture`` is the fixture the strategy scanned (``spin_target`` or ``qa_cube``), for the
    advice. The message lists every parameter over its limit and the estimated range noise.
    """
    problems = sigma_problems(result, limits, skip)
    if not problems:
        return
    noise = result.diagnostics.get("range_noise_m")
    seen = (
        f" (range noise {float(noise) * 1e3:.2f} mm estimated from the scan)"
        if isinstance(noise, float) and math.isfinite(noise)
        else ""
    )
    raise ObservabilityError(
        f"the {result.strategy} fine-tuning cannot determine the calibration well enough"
        f"{seen}: {'; '.join(problems)}. {ADVICE.get(fixture, 'Re-place the fixture and retry.')}"
    )


# --- the accuracy budget ----------------------------------------------------------------------
def predict(
    result: CalibrationResult,
    accuracy: AccuracySettings,
    platter: PlatterGeometry,
    *,
    known: tuple[str, ...] = (),
) -> PredictedError:
    """The reconstruction error ``result`` predicts over the budget's work volume
    (:func:`calstation.engine.accuracy.predicted_error`), from its covariance and σ, with the
    bound of any remaining bias it declares (``diagnostics["bias_bound"]``, per parameter).

    ``known``: parameters taken as exactly known (their uncertainty, and what it implies for the
    others through the covariance, removed): what the error would be if a later measurement
    pinned them down, e.g. ry after the cube scan.
    """
    from calstation.engine.accuracy import predicted_error

    sigma = dict(result.sigma)
    covariance = result.diagnostics.get("covariance")
    bias = dict(result.diagnostics.get("bias_bound") or {})
    for name in known:
        covariance, sigma = _conditioned(covariance, sigma, name)
        bias.pop(name, None)
    return predicted_error(
        result.H, sigma, covariance,
        radius=accuracy.work_radius(platter), height=accuracy.height, level=accuracy.level,
        bias=bias or None,
    )


def _conditioned(
    covariance: CovarianceRecord | None, sigma: dict[str, float], name: str
) -> tuple[CovarianceRecord | None, dict[str, float]]:
    """The covariance and σ once parameter ``name`` is known exactly (Schur complement)."""
    sigma = {**sigma, name: math.nan}
    if covariance is None or name not in covariance.get("parameters", []):
        return covariance, sigma
    names = list(covariance["parameters"])
    C = np.asarray(covariance["matrix"], dtype=np.float64)
    i = names.index(name)
    if C[i, i] > 0:
        C = C - np.outer(C[:, i], C[i, :]) / C[i, i]
    keep = [k for k in range(len(names)) if k != i]
    for k in keep:
        sigma[names[k]] = math.sqrt(max(float(C[k, k]), 0.0))
    reduced: CovarianceRecord = {"parameters": [names[k] for k in keep],
                                 "matrix": C[np.ix_(keep, keep)].tolist()}
    return reduced, sigma


def accuracy_problem(predicted: PredictedError, accuracy: AccuracySettings) -> str | None:
    """Why ``predicted`` is refused against the budget, or None when it is within it."""
    if not math.isfinite(predicted.max_m):
        return ("the predicted reconstruction error cannot be computed: the calibration has no "
                "σ for any parameter that distorts the reconstruction")
    if predicted.max_m <= accuracy.max_error:
        return None
    return (
        f"predicted reconstruction error {predicted.max_m * 1e3:.3f} mm "
        f"({accuracy.level:.0%}, over the work volume of {predicted_volume(predicted)}) > "
        f"{accuracy.max_error * 1e3:.3f} mm (calibration.accuracy.max_error)"
    )


def predicted_volume(predicted: PredictedError) -> str:
    """The work volume as the operator reads it: ``r 293 mm × h 150 mm``."""
    if predicted.points.size == 0:
        return "—"
    radius = float(np.max(np.hypot(predicted.points[:, 1], predicted.points[:, 2])))
    height = float(np.max(predicted.points[:, 0]))
    return f"r {radius * 1e3:.0f} mm × h {height * 1e3:.0f} mm"
