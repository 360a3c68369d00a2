"""The observability gate: refuse a calibration whose σ says the data do not determine it.

A fine-tuning always returns numbers; whether they mean anything depends on what the scan could
see. Each strategy reports a 1σ per parameter (docs/algorithms.md says how it is obtained);
:func:`check_sigma` compares them with the recipe's ``calibration.max_sigma`` and raises
:class:`~calstation.errors.ObservabilityError`, naming each parameter, its σ and its limit and
saying what to do, rather than hand the operator a silent guess.
"""

from __future__ import annotations

import math

from calstation.engine.result import CalibrationResult
from calstation.engine.settings import SigmaLimits
from calstation.errors import ObservabilityError

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
        ("ry", math.radians(limits.ry_deg), math.degrees(1.0), "°"),
        ("rz", math.radians(limits.rz_deg), math.degrees(1.0), "°"),
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
        if sigma > limit:
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
    (:func:`calstation.plugins.cost_strategies.fine_tune_with_cube`): that step's
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
