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
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from calstation.engine.frames import PARAMETER_NAMES, Extrinsics
from calstation.engine.rangemodel import (
    ESTIMATED_NAMES,
    RANGE_NAMES,
    RangeModelName,
    range_result_fields,
)
from calstation.engine.residuals import TermResponse, TrendRecord, in_check, unmodelled
from calstation.engine.result import CalibrationResult

if TYPE_CHECKING:
    from calstation.engine.certificate import Certificate
    from calstation.engine.cube import CubeCheck
    from calstation.engine.cubefit import KnownSizeFit
    from calstation.engine.fusion import Disagreement, Fused
    from calstation.engine.periodicity.covariance import CovarianceRecord
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
    details: dict[str, object]


def disagreement_sigma(sigma_ry: float, twist: float, twist_sigma: float) -> float:
    """How many combined σ the cube's ry correction ``twist`` (rad, 1σ ``twist_sigma``) lies
    from the fine-tuning's ry (1σ ``sigma_ry``)."""
    return abs(twist) / math.sqrt(sigma_ry**2 + twist_sigma**2)


def combine_with_cube(
    H: Extrinsics, covariance: CovarianceRecord | None, twist: float, twist_sigma: float
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
    details: dict[str, object] = {
        "ry_spin_target": H.ry,
        "sigma_ry_spin_target": math.sqrt(max(var_ry, 0.0)),
        "ry_cube": H.ry + twist,
        "sigma_ry_cube": twist_sigma,
        "disagreement_sigma": z,
    }
    if z > CONSISTENCY_SIGMA:
        return None
    from calstation.engine.fusion import kalman_update

    gain, C_new = kalman_update(C, i, twist_sigma**2)
    x = H.as_vector()
    for k, name in enumerate(names):
        x[PARAMETER_NAMES.index(name)] += gain[k] * twist
    sigma = {n: math.nan for n in PARAMETER_NAMES}
    for k, name in enumerate(names):
        sigma[name] = math.sqrt(max(float(C_new[k, k]), 0.0))
    details["covariance"] = {"parameters": names, "matrix": C_new.tolist()}
    return JointRy(Extrinsics.from_vector(x), sigma, details)


def ry_with_cube(
    H: Extrinsics,
    covariance: CovarianceRecord | None,
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
    cube: Scan | None,
    geometry: CubeGeometry,
    qa: QALimits,
    *,
    platter_radius: float,
    max_sigma_ry: float | None,
    progress: Callable[[str, float], None] | None = None,
    prepared: SpinScan | None = None,
    refit: Callable[[CalibrationResult], CalibrationResult] | None = None,
    certificate: Certificate | None = None,
    encoder_accuracy: float = 0.0,
) -> tuple[CalibrationResult, CubeCheck, str | None]:
    """A spin-target fine-tuning ``result`` with ry combined from the cube scan ``cube``, as
    the station does at its cube step: (the combined result, strategy ``<name>+cube``, with
    ``result``'s diagnostics and the ``joint`` details, or ``result`` itself when nothing could
    be combined; the cube check under that H; the failure of :func:`ry_with_cube` or None).
    ``geometry`` and ``qa`` are the cube's and the check's settings, ``max_sigma_ry`` the ry
    gate (rad); ``prepared`` the cube scan's returns already prepared
    (:func:`calstation.engine.cube.check_cube`). A ``result`` that holds the lidar's range model
    is combined with it instead (:func:`combine_range_with_cube_scan`, ``refit``,
    ``certificate``, ``encoder_accuracy``)."""
    from calstation.engine.cube import check_cube

    if result.range_offset is not None:
        return combine_range_with_cube_scan(result, cube, geometry, qa,
                                            platter_radius=platter_radius, progress=progress,
                                            prepared=prepared, refit=refit,
                                            certificate=certificate,
                                            encoder_accuracy=encoder_accuracy)
    result = with_encoder_error(result, encoder_accuracy)
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


def with_encoder_error(result: CalibrationResult, accuracy: float) -> CalibrationResult:
    """``result`` (one fixture's: a spin target's without the lidar's range model, or the
    shape strategy's cube fit) with what the encoder's angle error of stated ``accuracy``
    (rad) may move it by in its covariance and σ: its ``diagnostics["follows_encoder"]`` (per
    radian of each coefficient) times each coefficient's σ (:func:`calstation.engine.encoder.
    coefficient_sigma`), as the covariance it is. With one fixture, nothing tells the
    encoder's error apart; itself when the accuracy is zero, the result says nothing of how it
    follows, or it was added once."""
    from calstation.engine.encoder import coefficient_sigma, columns

    follows = result.diagnostics.get("follows_encoder")
    record = result.diagnostics.get("covariance")
    if accuracy <= 0 or not follows or record is None or "encoder_sigma" in result.diagnostics:
        return result
    names = [str(n) for n in record["parameters"]]
    sigma_c = coefficient_sigma(accuracy)
    G = columns(follows, names, sigma_c)
    extra = G @ G.T
    C = np.asarray(record["matrix"], dtype=np.float64) + extra
    # in quadrature with the σ as it was (which may hold a bias bound beside the covariance)
    sigma = dict(result.sigma)
    sigma.update({n: math.hypot(sigma[n], math.sqrt(max(float(extra[k, k]), 0.0)))
                  for k, n in enumerate(names) if n in PARAMETER_NAMES and n in sigma})
    diagnostics = {**result.diagnostics, "encoder_sigma": sigma_c,
                   "covariance": {"parameters": names, "matrix": C.tolist()}}
    return replace(result, sigma=sigma, diagnostics=diagnostics)


REFITS = 2
"""Times, at most, the spin target's fine-tuning is run again from the combined estimate (its
range terms and ty held there) before the last combination: the spin scan's response to the
range terms is not linear over millimetres of offset."""

REFIT_SETTLED = 0.25
"""A refit that moved the combination by less than this, in its σ, in every parameter and
range term, is the last: the next moves it far less. On the default simulated run
(`benchmarks/calibration.py`) the first refit moved it by 0.104σ (the incidence bias; H by
0.047σ at most) and the second by 0.0065σ."""


def _moved(before: Fused, after: Fused) -> float:
    """How far ``after`` lies from ``before``: the largest difference of a parameter, in
    ``after``'s σ of it."""
    a, b, sigma = before.vector, after.vector, after.sigma
    moved = [abs(b[ESTIMATED_NAMES.index(n)] - a[ESTIMATED_NAMES.index(n)]) / sigma[n]
             for n in after.names if sigma[n] > 0]
    return float(max(moved, default=0.0))


def combine_range_with_cube_scan(
    result: CalibrationResult,
    cube: Scan | None,
    geometry: CubeGeometry,
    qa: QALimits,
    *,
    platter_radius: float,
    progress: Callable[[str, float], None] | None = None,
    prepared: SpinScan | None = None,
    refit: Callable[[CalibrationResult], CalibrationResult] | None = None,
    certificate: Certificate | None = None,
    encoder_accuracy: float = 0.0,
) -> tuple[CalibrationResult, CubeCheck, str | None]:
    """A spin-target fine-tuning ``result`` that holds the lidar's range model, combined with
    the cube scan as the station does at its cube step: the known-size cube fit with the range
    model (:func:`calstation.engine.cubefit.range_size_fit`, from ``result``) and ``result``
    combined in information form (:mod:`calstation.engine.fusion`), which gives the range
    offset and the incidence bias the cube's edge and square faces, the scale error the cube's
    size, ty the cube's top, and ry the cube's side faces. ``refit(start)``: the spin target's
    fine-tuning run again from a combined estimate, holding its range terms and ty
    (:data:`REFITS` times). The lidar's ``certificate`` is combined with the result
    (:func:`calstation.engine.certificate.with_certificate`) before the check; the turntable
    encoder's stated ``encoder_accuracy`` (rad) is carried through the combination
    (:mod:`calstation.engine.encoder`). Returns (the
    combined result, strategy ``<name>+cube``, or ``result`` when they could not be combined,
    with why in ``diagnostics["joint"]``; the cube check under it; why not, or None)."""
    from calstation.engine.certificate import with_certificate
    from calstation.engine.cube import check_cube
    from calstation.engine.spinscan import prepared_or_read

    if progress is not None:
        progress("fitting the cube with the lidar's range model", 0.2)
    scan = prepared_or_read(cube, prepared)
    combined, failure, residuals = combine_range_with_cube(
        result, scan, geometry, platter_radius=platter_radius, refit=refit, progress=progress,
        encoder_accuracy=encoder_accuracy)
    if failure is None:
        combined, failure = with_certificate(combined, certificate)
    if progress is not None:
        progress("measuring the cube", 0.8)
    check = check_cube(cube, combined.H, geometry, qa, platter_radius=platter_radius,
                       prepared=prepared, range_model=combined.range_model)
    if not check.passed and failure is None:
        if progress is not None:
            progress("measuring the cube with the range terms moved by their uncertainty", 0.9)
        failure = check_failure(cube, scan, combined, check, geometry, qa,
                                platter_radius=platter_radius, residuals=residuals)
    return combined, check, failure


def check_failure(
    cube: Scan | None, scan: SpinScan, result: CalibrationResult, check: CubeCheck,
    geometry: CubeGeometry, qa: QALimits, *, platter_radius: float,
    residuals: Mapping[str, TrendRecord],
) -> str | None:
    """What the lidar's range error may do to ``check``, a cube check under ``result`` that
    failed (:func:`calstation.engine.residuals.in_check`): how far its failed figures follow
    the range terms' uncertainty (:func:`range_responses`, on ``scan``, the cube scan's
    prepared returns), and the known-size fit's ``residuals`` trends; None when ``result``'s
    range model has no clear term and the residuals no trend. The cube's shape alone is then
    what the check names."""
    return in_check(range_responses(cube, scan, result, check, geometry, qa,
                                    platter_radius=platter_radius), residuals)


SIGNIFICANT = 3.0
"""A range term further than this many σ from zero is one the lidar clearly has: a failed cube
check says what its uncertainty does to the check (:func:`range_responses`)."""

_FIELDS = {"incidence_bias": "incidence", "range_offset": "offset", "range_scale": "scale"}
"""The range terms' names in a result, and their :class:`~calstation.engine.rangemodel.
RangeModel` fields."""


def range_responses(
    cube: Scan | None, scan: SpinScan, result: CalibrationResult, check: CubeCheck,
    geometry: CubeGeometry, qa: QALimits, *, platter_radius: float,
) -> list[TermResponse]:
    """How far each figure that failed ``check`` (the cube check under ``result``,
    :func:`calstation.engine.cube.failed_figures`) moves when each range term of ``result``
    that is clearly not zero (beyond :data:`SIGNIFICANT` σ) moves by its uncertainty, either
    way: its σ, and for the incidence bias :data:`INCIDENCE_MODEL` of it beside, the share of
    its effect the bias's shape may miss. Each is the check again under the same H (its edges,
    flatness and perpendicularity: no box, no twist) on ``scan``, the cube scan's prepared
    returns, with a memo of its own. Empty when no figure failed or no term is clear; a term
    under which the cube is no longer found (never seen) is left out."""
    from calstation.engine.cube import check_cube, failed_figures
    from calstation.errors import VerificationError

    failed = failed_figures(check, qa)
    if not failed:
        return []
    model = result.range_model
    out: list[TermResponse] = []
    for name, field in _FIELDS.items():
        value, sigma = getattr(result, name), getattr(result, f"sigma_{name}")
        if value is None or sigma is None or not (math.isfinite(sigma) and sigma > 0) \
                or abs(value) <= SIGNIFICANT * sigma:
            continue
        model_error = INCIDENCE_MODEL * abs(value) if name == "incidence_bias" else 0.0
        step = math.hypot(sigma, model_error)
        try:
            moved = [check_cube(cube, result.H, geometry, qa, platter_radius=platter_radius,
                                prepared=replace(scan, memo={}),
                                range_model=replace(model, **{field: value + sign * step}),
                                edges_only=True)
                     for sign in (-1.0, 1.0)]
        except VerificationError:
            continue
        out.append({
            "name": name, "value": float(value), "sigma": float(sigma),
            "model_error": model_error, "step": step,
            "figures": {f: {"value": float(getattr(check, f)), "limit": limit,
                            "at": [float(getattr(m, f)) for m in moved]}
                        for f, limit in failed.items()},
        })
    return out


def combine_range_with_cube(
    result: CalibrationResult,
    scan: SpinScan,
    geometry: CubeGeometry,
    *,
    platter_radius: float,
    refit: Callable[[CalibrationResult], CalibrationResult] | None = None,
    progress: Callable[[str, float], None] | None = None,
    encoder_accuracy: float = 0.0,
) -> tuple[CalibrationResult, str | None, Mapping[str, TrendRecord]]:
    """The combination of :func:`combine_range_with_cube_scan` without the cube check: the
    known-size cube fit with the range model on the cube's prepared returns ``scan`` (the whole
    scan, or the turns so far), combined with ``result``. Returns (the combined result, or
    ``result`` when they could not be combined; why not, or None; the fit's residual trends)."""
    from calstation.errors import FineTuningError

    try:
        fit = _range_size_fit(result, scan, geometry, platter_radius, encoder_accuracy > 0)
    except FineTuningError as exc:
        return result, f"the cube could not add to the range model: {exc}", {}
    combined, failure = _combine_with_fit(result, fit, refit, progress, encoder_accuracy)
    return combined, failure, fit.residuals


def _range_size_fit(
    result: CalibrationResult, scan: SpinScan, geometry: CubeGeometry, platter_radius: float,
    encoder: bool = False,
) -> KnownSizeFit:
    """The known-size cube fit with the range model from ``result`` on ``scan``, kept in the
    scan's ``memo``: the cube scan's fit made while it turned (on the turns that met the budget)
    is the one the step after it combines, not made again."""
    from calstation.engine.cubefit import KnownSizeFit, known_size_fit
    from calstation.errors import FineTuningError

    model: RangeModelName = "offset+scale" if result.range_scale is not None else "offset"
    incidence = result.incidence_bias is not None
    key = (result.H.as_vector().tobytes(), result.range_model.as_vector().tobytes(), model,
           incidence, repr(geometry), platter_radius, encoder)
    kept = scan.memo.get("range_size_fit")
    if isinstance(kept, tuple) and kept[0] == key:
        if isinstance(kept[1], FineTuningError):
            raise kept[1]
        if isinstance(kept[1], KnownSizeFit):
            return kept[1]
    try:
        fit = known_size_fit(scan, result.H, geometry, platter_radius=platter_radius,
                             range_model=model, start_range=result.range_model,
                             incidence=incidence, encoder=encoder)
    except FineTuningError as exc:
        scan.memo["range_size_fit"] = (key, exc)
        raise
    scan.memo["range_size_fit"] = (key, fit)
    return fit


def _combine_with_fit(
    result: CalibrationResult, fit: KnownSizeFit,
    refit: Callable[[CalibrationResult], CalibrationResult] | None,
    progress: Callable[[str, float], None] | None,
    encoder_accuracy: float = 0.0,
) -> tuple[CalibrationResult, str | None]:
    """``result`` (the spin target's) and the cube's ``fit`` combined, the spin target's
    fine-tuning run again from the combination (``refit``) in between: (the combined result,
    or ``result`` with the reason in its diagnostics; the failure or None). The encoder's
    angle error, of stated ``encoder_accuracy`` (rad), moves both; the combination carries it
    (:meth:`calstation.engine.fusion.Estimate.with_encoder`)."""
    from calstation.engine.encoder import coefficient_sigma
    from calstation.engine.fusion import Estimate, consistent, fuse

    total = fit.total_covariance()
    if total is None:
        return result, "the cube's fit has no covariance: its faces do not fix the calibration"
    sigma_encoder = coefficient_sigma(encoder_accuracy)
    cube = Estimate.of(fit.H, fit.range_model, total).with_encoder(fit.encoder_direction,
                                                                   sigma_encoder)
    spin = result
    shape_error = INCIDENCE_MODEL * abs(fit.range_model.incidence)
    before: Fused | None = None
    for k in range(REFITS + 1):
        fused = fuse(Estimate.of(spin.H, spin.range_model, spin.diagnostics["covariance"],
                                 spin.diagnostics.get("follows", {}))
                     .with_model_error("incidence_bias", shape_error)
                     .with_encoder(spin.diagnostics.get("follows_encoder"), sigma_encoder),
                     cube)
        if refit is None or k == REFITS or (before is not None
                                            and _moved(before, fused) < REFIT_SETTLED):
            break
        before = fused
        if progress is not None:
            progress("the spin target again, from the cube's range model", 0.3 + 0.15 * k)
        spin = refit(_combined(spin, fit, fused))
    # the refits are the strategy's alone: what ``result`` estimated beside H stays with it
    combined = replace(_combined(spin, fit, fused), encoder_latency_s=result.encoder_latency_s,
                       sigma_encoder_latency_s=result.sigma_encoder_latency_s)
    if consistent(fused):
        return combined, None
    diagnostics = {**result.diagnostics, "joint": combined.diagnostics["joint"]}
    return replace(result, diagnostics=diagnostics), range_disagreement(
        fused.disagreement, fit.residuals)


INCIDENCE_MODEL = 0.2
"""How much of the incidence bias's effect on the spin target its correction may miss: the
spin target's surfaces are known only from local planes through its returns, and the bias's
shape, c·(1/cos θ − 1), is a model. On the simulator the spin target's tx still moved by about
12 % of what the whole bias would move it (0.05 mm of 0.47 mm at 0.5 mm of bias at 60°)."""


def range_disagreement(
    disagreement: Disagreement, residuals: Mapping[str, TrendRecord] | None = None
) -> str:
    """The refusal when the spin target and the cube disagree (:mod:`~calstation.engine.
    fusion`), naming what differs most; the lidar's range error when the cube's residuals show
    one the range model does not hold (:func:`calstation.engine.residuals.unmodelled`), or when
    the offset or the scale is what differs."""
    sigmas = disagreement["sigmas"]
    worst = sorted(sigmas, key=lambda n: -abs(sigmas[n]))[:2]
    said = ", ".join(f"{n} by {sigmas[n]:+.1f} σ" for n in worst)
    head = (f"the spin target and the QA cube disagree on the calibration (χ² "
            f"{disagreement['chi2']:.1f} on {disagreement['dof']} parameters, p = "
            f"{disagreement['p']:.1e}; most on {said})")
    seen = unmodelled(residuals or {})
    if seen:
        return (f"{head}: the lidar's range error is not what its range model says — on the "
                f"cube's faces, {'; '.join(seen)}")
    if worst and worst[0] in ("range_offset", "range_scale"):
        return (f"{head}: the lidar's range error is not what its range model says — a bias "
                "that depends on the surface (its reflectivity or the angle the rays meet it) "
                "reads differently on the two fixtures. See the residuals against incidence and "
                "range in the report; use fixtures of one finish, or re-seat the cube so its "
                "faces meet the rays less obliquely")
    return (f"{head}: re-place the spin target off-centre and re-seat the cube, then re-run the "
            "calibration; if they disagree again, check the turntable's encoder: a code disc "
            "mounted off-centre reads the platter's angle with an error once per turn, which "
            "moves the spin target's estimate and the cube's differently")


def _combined(result: CalibrationResult, fit: KnownSizeFit, fused: Fused) -> CalibrationResult:
    """The combined :class:`CalibrationResult` of :func:`combine_range_with_cube_scan`."""
    sigma = {n: math.nan for n in PARAMETER_NAMES}
    fused_sigma = fused.sigma
    sigma.update({n: v for n, v in fused_sigma.items() if n in PARAMETER_NAMES})
    details = {
        "spin_target": {"H": result.H.as_dict(), **result.range_fields(),
                        "sigma": dict(result.sigma)},
        "cube": {"H": fit.H.as_dict(), "range_offset": fit.range_model.offset,
                 "range_scale": fit.range_model.scale,
                 "incidence_bias": fit.range_model.incidence, "sigma": fit.sigma,
                 "bias_bound": fit.bias, "known_size": fit.details,
                 "residuals": fit.residuals},
        "disagreement": fused.disagreement,
    }
    diagnostics = {**result.diagnostics, "joint": details, "covariance": fused.record(),
                   "bias_bound": {}}
    terms = [ESTIMATED_NAMES.index(n) for n in fused.names if n in RANGE_NAMES]
    combined = replace(result, H=fused.H, sigma=sigma, strategy=f"{result.strategy}+cube",
                       diagnostics=diagnostics)
    return combined.with_range(range_result_fields(fused.vector, dict(fused_sigma), terms))


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
    if "cube" in d:  # combined with the lidar's range model (combine_range_with_cube_scan)
        return range_summary(combined)
    return (f"ry from the spin target {math.degrees(d['ry_spin_target']):.3f}° ± "
            f"{math.degrees(d['sigma_ry_spin_target']):.3f}°, from the cube "
            f"{math.degrees(d['ry_cube']):.3f}° ± {math.degrees(d['sigma_ry_cube']):.3f}° → "
            f"combined {math.degrees(combined.H.ry):.3f}° ± "
            f"{math.degrees(combined.sigma['ry']):.3f}°")


def range_summary(result: CalibrationResult) -> str:
    """One line of the lidar's range model and ry after the spin target and the cube were
    combined (millimetres, degrees)."""
    from calstation.engine.rangemodel import describe

    parts = [describe(result.range_fields(), result.diagnostics.get("certificate"))
             or "no range model"]
    parts.append(f"ry {math.degrees(result.H.ry):.3f}° ± "
                 f"{math.degrees(result.sigma.get('ry', math.nan)):.3f}°")
    return "the spin target and the QA cube combined: " + ", ".join(parts)
