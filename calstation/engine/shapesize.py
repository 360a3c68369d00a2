"""The shape strategy's last stage: the known-size cube fit (:mod:`calstation.engine.cubefit`),
from the box cost's result or, with the lidar's range model and a start close enough, from the
start itself (calstation; docs/algorithms.md, docs/performance.md).

With the range model, the known-size fit settles from a start several millimetres off on its
own (its rounds on a part of the returns label the faces against the model until it moves H by
less than 0.1 mm), and the box cost before it only moved the start it begins from: on a start
whose cube's box is already within :data:`calstation.engine.shape.COARSE_GATE_M` plus 6σ of
range noise of the recipe's edge (the gate the coarse alignment uses), the shape strategy fits
from the start and skips the box cost, its static test and its σ. A start further off, or a fit
that fails from it, takes the box cost's path as before.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from calstation.engine.cubefit import KnownSizeFit, known_size_fit
from calstation.engine.frames import PARAMETER_NAMES, Extrinsics
from calstation.engine.rangemodel import RangeModelName, estimated_indices, range_result_fields
from calstation.engine.result import CalibrationResult
from calstation.engine.settings import CubeGeometry
from calstation.engine.spinscan import SpinScan
from calstation.errors import FineTuningError


def with_known_size(
    result: CalibrationResult,
    scan: SpinScan,
    cube: CubeGeometry,
    platter_radius: float,
    estimate_ry: bool,
    range_model: RangeModelName = "none",
    incidence: bool = False,
    encoder: bool = False,
) -> tuple[CalibrationResult, KnownSizeFit | None]:
    """``result`` after the known-size cube fit (:mod:`calstation.engine.cubefit`) from its
    H: the fit's H, σ and covariance, ``diagnostics.known_size`` (and the range model it
    estimated); unchanged but for the reason in the diagnostics (and None) when the cube's faces
    could not be labelled."""
    try:
        fit = known_size_fit(
            scan, result.H, cube, platter_radius=platter_radius, estimate_ry=estimate_ry,
            range_model=range_model, incidence=incidence, encoder=encoder,
        )
    except FineTuningError as exc:
        result.diagnostics["known_size"] = {"used": False, "reason": str(exc)}
        return result, None
    return with_fit(result, fit, estimate_ry, range_model, incidence, from_box=True), fit


def from_start(
    scan: SpinScan,
    start: Extrinsics,
    cube: CubeGeometry,
    platter_radius: float,
    gate: float,
    range_model: RangeModelName,
    incidence: bool = False,
    encoder: bool = False,
) -> CalibrationResult | None:
    """The shape strategy's result from the known-size fit with the range model made from
    ``start`` itself, when the cube's box under it is within ``gate`` plus 6σ of range noise of
    the recipe's edge (:func:`calstation.engine.cubefit.range_size_fit`); None when it is not,
    or when the fit fails from there (the box cost's path then runs)."""
    try:
        fit = known_size_fit(
            scan, start.with_(rx=0.0), cube, platter_radius=platter_radius, estimate_ry=True,
            range_model=range_model, incidence=incidence, encoder=encoder, gate=gate,
        )
    except FineTuningError:
        return None
    begun = CalibrationResult(
        H=start.with_(rx=0.0),
        sigma={n: math.nan for n in PARAMETER_NAMES},
        cost=math.nan,
        iterations=int(fit.details["evaluations"]),  # type: ignore[arg-type]
        strategy="shape",
        diagnostics={
            "box": "none",
            "box_note": "the start's cube within the coarse gate: the known-size cube fit "
                        "from the start, without the box cost",
            "estimate_ry": True,
            "range_noise_m": fit.details["range_noise_m"],
            "start_H": start.as_dict(),
        },
    )
    return with_fit(begun, fit, True, range_model, incidence, from_box=False)


def with_fit(
    result: CalibrationResult, fit: KnownSizeFit, estimate_ry: bool,
    range_model: RangeModelName, incidence: bool, *, from_box: bool,
) -> CalibrationResult:
    """``result`` (the box cost's, ``from_box``, or the start's) with the known-size fit's H,
    σ, covariance and details (and the range model it estimated)."""
    diagnostics = dict(result.diagnostics)
    diagnostics.update(known_size=fit.details, covariance=fit.covariance, bias_bound=fit.bias)
    if from_box:
        diagnostics["box_H"] = result.H.as_dict()
    if estimate_ry:
        diagnostics["ry_source"] = "known-size cube"
    if fit.encoder_direction is not None:
        diagnostics["follows_encoder"] = fit.encoder_direction
    sigma = dict(result.sigma)
    sigma.update({n: v for n, v in fit.sigma.items() if math.isfinite(v) and n in sigma})
    result = replace(result, H=fit.H, sigma=sigma, diagnostics=diagnostics)
    if range_model != "none":
        # the result is the fit's: its cost is the fit's mean squared range error (m²), on
        # either path, so that results from several starts compare alike
        rms = float(fit.details["rms_range_error_m"])  # type: ignore[arg-type]
        diagnostics.update(range_model=range_model, gauge="platter", gauge_note=(
            "origin along the axis fixed by the platter top in the cube scan (x_P = 0)"),
            cost_terms="the known-size cube fit's mean squared range error")
        terms = estimated_indices(range_model, incidence)
        result = replace(result, cost=rms**2).with_range(range_result_fields(
            np.concatenate([fit.H.as_vector(), fit.range_model.as_vector()]), dict(fit.sigma),
            terms))
    return result
