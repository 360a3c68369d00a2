"""ry from the spin target and the QA cube together.

The periodicity cost sees ry weakly (docs/algorithms.md); the cube's side faces see it well: an
ry error twists them (:func:`calstation.engine.cube.face_twist`). Every run scans both, so the
station combines them: the twist measured on the cube scan under the fine-tuned H is a
measurement of the ry correction, ``ry_cube = ry_fine + twist`` with its σ, and it updates the
fine-tuning's estimate through its covariance (a Kalman update), which also moves the parameters
correlated with ry (tz above all: the spin target fixes tz + ry·h at its own height h).

When the two disagree by more than :data:`CONSISTENCY_SIGMA` combined σ they are not combined:
one of them is wrong, and the cube check's twist limit reports it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from calstation.engine.frames import PARAMETER_NAMES, Extrinsics
from calstation.engine.result import CalibrationResult

if TYPE_CHECKING:
    from calstation.engine.cube import CubeCheck
    from calstation.engine.scan import Scan
    from calstation.engine.settings import CubeGeometry, QALimits
    from calstation.engine.spinscan import SpinScan

MORE_DATA = (
    "Scan more turns (steps.spin_scan.revolutions and steps.cube_scan.revolutions: the σ falls "
    "as returns are added), re-place the spin target off-centre if it stood centred, and "
    "re-seat the cube so that two side faces face the lidar; or, if the station's accuracy "
    "need allows, raise calibration.max_sigma.ry_deg"
)
"""What to do when ry stays undetermined after the cube scan."""

CONSISTENCY_SIGMA = 3.0
"""Largest disagreement (in combined σ) between the two ry estimates that is still combined."""


@dataclass(frozen=True)
class JointRy:
    """The combined estimate: H and σ per parameter (SI), and how it was obtained."""

    H: Extrinsics
    sigma: dict[str, float]
    details: dict[str, Any]


def disagreement_sigma(sigma_ry: float, twist: float, twist_sigma: float) -> float:
    """How many combined σ the cube's ry correction ``twist`` (rad, 1σ ``twist_sigma``) lies
    from the fine-tuning's ry (1σ ``sigma_ry``)."""
    return abs(twist) / math.sqrt(sigma_ry**2 + twist_sigma**2)


def combine_with_cube(
    H: Extrinsics, covariance: dict[str, Any] | None, twist: float, twist_sigma: float
) -> JointRy | None:
    """Update H (with its ``covariance`` record: ``parameters`` names and ``matrix``, SI) with
    the cube's ry measurement ``H.ry + twist`` (rad) of 1σ ``twist_sigma`` (rad).

    None when there is nothing to combine (no covariance, ry not estimated, a twist that could
    not be measured) or when the two disagree by more than :data:`CONSISTENCY_SIGMA` σ.
    """
    if covariance is None or not (math.isfinite(twist) and math.isfinite(twist_sigma)):
        return None
    names = list(covariance.get("parameters", []))
    if "ry" not in names or twist_sigma <= 0:
        return None
    C = np.asarray(covariance["matrix"], dtype=np.float64)
    i = names.index("ry")
    var_ry = float(C[i, i])
    z = disagreement_sigma(math.sqrt(max(var_ry, 0.0)), twist, twist_sigma)
    details: dict[str, Any] = {
        "ry_spin_target": H.ry,
        "sigma_ry_spin_target": math.sqrt(max(var_ry, 0.0)),
        "ry_cube": H.ry + twist,
        "sigma_ry_cube": twist_sigma,
        "disagreement_sigma": z,
    }
    if z > CONSISTENCY_SIGMA:
        return None
    gain = C[:, i] / (var_ry + twist_sigma**2)
    x = H.as_vector()
    for k, name in enumerate(names):
        x[PARAMETER_NAMES.index(name)] += gain[k] * twist
    C_new = C - np.outer(gain, C[i, :])
    sigma = {n: math.nan for n in PARAMETER_NAMES}
    for k, name in enumerate(names):
        sigma[name] = math.sqrt(max(float(C_new[k, k]), 0.0))
    details["covariance"] = {"parameters": names, "matrix": C_new.tolist()}
    return JointRy(Extrinsics.from_vector(x), sigma, details)


def ry_with_cube(
    H: Extrinsics,
    covariance: dict[str, Any] | None,
    sigma_ry: float,
    twist: float,
    twist_sigma: float,
    limit: float | None,
) -> tuple[JointRy | None, str | None]:
    """The station's ry decision after the cube scan of a spin-target fine-tuning: H with its
    ``covariance`` record and ry σ ``sigma_ry`` (rad; NaN when the strategy held ry), the cube's
    twist and its σ under H (rad), the recipe's optional ry σ limit (rad; None: no limit, the
    accuracy budget decides).

    Returns (the combined estimate or None, a failure or None). It fails when the two
    estimates disagree by more than :data:`CONSISTENCY_SIGMA`, or when ry's σ (combined, or
    the spin target's alone when the cube could not add to it) exceeds ``limit``.
    """
    joint = combine_with_cube(H, covariance, twist, twist_sigma)
    if joint is None:
        if math.isfinite(twist) and math.isfinite(twist_sigma) and math.isfinite(sigma_ry):
            z = disagreement_sigma(sigma_ry, twist, twist_sigma)
            if z > CONSISTENCY_SIGMA:
                return None, (
                    f"the spin target and the cube disagree on ry by {math.degrees(twist):+.3f}° "
                    f"({z:.1f} σ): re-place the spin target off-centre and re-run the "
                    "calibration, or re-seat the cube"
                )
        if limit is not None and math.isfinite(sigma_ry) and sigma_ry > limit:  # NaN: held
            return None, (
                f"ry is not determined: σ {math.degrees(sigma_ry):.3f}° > "
                f"{math.degrees(limit):.3f}° and the cube's side faces could not add to it. "
                f"{MORE_DATA}"
            )
        return None, None
    if limit is not None and joint.sigma["ry"] > limit:
        return joint, (
            f"ry is not determined well enough even with the cube: σ "
            f"{math.degrees(joint.sigma['ry']):.3f}° > {math.degrees(limit):.3f}° "
            f"(calibration.max_sigma.ry_deg). {MORE_DATA}"
        )
    return joint, None


def combine_with_cube_scan(
    result: CalibrationResult,
    cube: Scan,
    geometry: CubeGeometry,
    qa: QALimits,
    *,
    platter_radius: float,
    max_sigma_ry: float | None,
    progress: Callable[[str, float], None] | None = None,
    prepared: SpinScan | None = None,
) -> tuple[CalibrationResult, CubeCheck, str | None]:
    """A spin-target fine-tuning ``result`` with ry combined from the cube scan ``cube``, as
    the station does at its cube step: (the combined result, strategy ``<name>+cube``, with
    ``result``'s diagnostics and the ``joint`` details, or ``result`` itself when nothing could
    be combined; the cube check under that H; the failure of :func:`ry_with_cube` or None).
    ``geometry`` and ``qa`` are the cube's and the check's settings, ``max_sigma_ry`` the ry
    gate (rad); ``prepared`` the cube scan's returns already prepared
    (:func:`calstation.engine.cube.check_cube`)."""
    from calstation.engine.cube import check_cube

    check = check_cube(cube, result.H, geometry, qa, platter_radius=platter_radius,
                       prepared=prepared)
    combined, failure = with_cube_ry(result, check, max_sigma_ry)
    if combined is result:
        return result, check, failure
    if progress is not None:
        progress("measuring the cube with ry from both scans", 0.6)
    # the combined H moves ry by a few hundredths of a degree: the cube's returns found under
    # the first are turned to it rather than found again
    check = check_cube(cube, combined.H, geometry, qa, platter_radius=platter_radius,
                       prepared=prepared, nearby=True)
    return combined, check, failure


def with_cube_ry(
    result: CalibrationResult, check: CubeCheck, max_sigma_ry: float | None
) -> tuple[CalibrationResult, str | None]:
    """``result`` with ry combined from the twist that ``check`` (the cube check under
    ``result.H``) measured: (the combined result, strategy ``<name>+cube``, or ``result`` itself
    when nothing could be combined; the failure of :func:`ry_with_cube` or None)."""
    joint, failure = ry_with_cube(
        result.H, result.diagnostics.get("covariance"), result.sigma.get("ry", math.nan),
        math.radians(check.twist_deg), math.radians(check.twist_sigma_deg), max_sigma_ry,
    )
    if joint is None:
        return result, failure
    diagnostics = {**result.diagnostics, "joint": joint.details,
                   "covariance": joint.details["covariance"]}
    combined = CalibrationResult(
        H=joint.H, sigma=joint.sigma, cost=result.cost, iterations=result.iterations,
        strategy=f"{result.strategy}+cube", timings=dict(result.timings),
        diagnostics=diagnostics,
        # the time offset barely depends on ry (calstation.engine.timeoffset): it carries over
        # (the station estimates it again under the combined H)
        encoder_latency_s=result.encoder_latency_s,
        sigma_encoder_latency_s=result.sigma_encoder_latency_s,
    )
    return combined, failure


def joint_summary(combined: CalibrationResult) -> str:
    """One line of what :func:`combine_with_cube_scan` combined (degrees)."""
    d = combined.diagnostics["joint"]
    return (f"ry from the spin target {math.degrees(d['ry_spin_target']):.3f}° ± "
            f"{math.degrees(d['sigma_ry_spin_target']):.3f}°, from the cube "
            f"{math.degrees(d['ry_cube']):.3f}° ± {math.degrees(d['sigma_ry_cube']):.3f}° → "
            f"combined {math.degrees(combined.H.ry):.3f}° ± "
            f"{math.degrees(combined.sigma['ry']):.3f}°")
