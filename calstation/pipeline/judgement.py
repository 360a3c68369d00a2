"""The judgement, the pipeline's last stage: the predicted error of a calibration against the
accuracy budget, the ``calibration.max_sigma`` gate, and what would help when it is refused.

The engine predicts the distortion a calibration's uncertainty allows over the recipe's work
volume (:func:`calstation.engine.observability.predict`); here that figure is kept with the
result (``diagnostics["predicted_error"]``), compared with ``calibration.accuracy.max_error``,
and, when the budget does not hold, turned into advice whose every number is computed: how many
turns, how slow a platter, how fast a line rate would make the data enough (the random part of
the error falls as 1/√data), and whether a taller spin target or another placement addresses
the parameter that limits the accuracy.
"""

from __future__ import annotations

import math
from dataclasses import replace

from calstation import display
from calstation.engine.accuracy import PredictedError, contributions, data_factor
from calstation.engine.observability import accuracy_problem, predict, predicted_volume
from calstation.engine.rangemodel import with_unmeasured_scale
from calstation.engine.result import CalibrationResult
from calstation.recipes import Recipe

MOST_TURNS = 20.0
"""The most turns a recipe may ask of a scan (``steps.*.max_revolutions``)."""


def with_prediction(
    result: CalibrationResult, recipe: Recipe, *, turns: float | None = None,
    known: tuple[str, ...] = (),
) -> tuple[CalibrationResult, PredictedError]:
    """``result`` with its predicted error in ``diagnostics["predicted_error"]`` (metres; the
    budget, the work volume and the turns it came from beside it), and the prediction."""
    accuracy = recipe.calibration.accuracy
    result = with_scale_uncertainty(result, recipe)
    predicted = predict(result, accuracy, recipe.fixtures.platter, known=known)
    record: dict[str, object] = {
        **predicted.as_dict(),
        "budget_m": accuracy.max_error,
        "work_volume": {"radius_m": accuracy.work_radius(recipe.fixtures.platter),
                        "height_m": accuracy.height},
    }
    if turns is not None:
        record["turns"] = turns
    if known:
        record["known"] = list(known)
    diagnostics = {**result.diagnostics, "predicted_error": record}
    return replace(result, diagnostics=diagnostics), predicted


def describe(predicted: PredictedError, recipe: Recipe) -> str:
    """One line for the operator: the predicted error beside its budget."""
    budget = recipe.calibration.accuracy.max_error
    verdict = "within" if predicted.max_m <= budget else "above"
    return (f"predicted reconstruction error {display.number('predicted_error', predicted.max_m)} "
            f"({display.percent(recipe.calibration.accuracy.level, 0)}, "
            f"{predicted_volume(predicted)}), {verdict} the budget of "
            f"{display.number('predicted_error', budget)}")


def budget_failure(
    result: CalibrationResult, predicted: PredictedError, recipe: Recipe, *, scan: str,
    turns: float,
) -> str | None:
    """The refusal of ``result`` against the budget, with what would help, or None."""
    problem = accuracy_problem(predicted, recipe.calibration.accuracy)
    if problem is None:
        return None
    scale = _scale_advice(result, predicted, recipe)
    if scale is not None:
        return f"{problem}. {scale}"
    return f"{problem}. {advice(result, predicted, recipe, scan=scan, turns=turns)}"


def _scale_advice(
    result: CalibrationResult, predicted: PredictedError, recipe: Recipe
) -> str | None:
    """When the lidar's scale error the recipe does not measure is what puts ``predicted``
    over the budget (it would be within with the scale known), what would help: more data of
    the same kind cannot."""
    sigma_scale = result.diagnostics.get("unmeasured_scale_sigma")
    if not sigma_scale:
        return None
    accuracy = recipe.calibration.accuracy
    known = predict(result, accuracy, recipe.fixtures.platter, known=("range_scale",))
    if not known.max_m <= accuracy.max_error:
        return None
    return (f"The lidar's range scale error, not measured, is what limits it: with it known the "
            f"predicted error would be {display.number('predicted_error', known.max_m)}; its "
            f"stated uncertainty of {float(sigma_scale) * 1e6:.0f} ppm "
            "(calibration.range_scale_sigma) moves where the lidar seems to stand by that "
            "fraction of its distance, and more turns do not reduce it. What would help (each "
            "alone): the lidar's scale from its calibration certificate, as a smaller "
            "calibration.range_scale_sigma; or measure it with H (calibration.range_model: "
            "offset+scale, from the QA cube's known size)"
            + "".join(f"; or {said}" for said in _certificate_advice(result, recipe)))


def advice(
    result: CalibrationResult, predicted: PredictedError, recipe: Recipe, *, scan: str,
    turns: float,
) -> str:
    """What would bring ``predicted`` within the budget, computed from the scan that gave it
    (``scan``: ``spin_scan`` or ``cube_scan``, taken over ``turns`` turns)."""
    accuracy = recipe.calibration.accuracy
    factor = data_factor(predicted, accuracy.max_error)
    on_cube = scan == "cube_scan" or _fits_the_cube(recipe)
    if not math.isfinite(factor):
        return _bias_advice(result, predicted, recipe, on_cube)
    cfg = getattr(recipe.steps, scan)
    say = []
    needed = math.ceil(turns * factor)
    if needed <= MOST_TURNS:
        say.append(f"scan {needed:g} turns (steps.{scan}.max_revolutions: {needed:g}; this scan "
                   f"took {turns:g})")
    else:
        say.append(f"{needed:.0f} turns would be needed, more than the {MOST_TURNS:g} a scan "
                   "may take")
    slower = abs(cfg.rpm) / factor
    if slower >= 0.5:
        say.append(f"turn the platter at {slower:.2g} rpm instead of {abs(cfg.rpm):g} "
                   f"(steps.{scan}.rpm)")
    sim = recipe.simulation
    if sim is not None and recipe.station.lidar.driver == "sim":
        rate = sim.lidar.line_rate_hz
        say.append(f"a lidar line rate of {rate * factor:.0f} lines/s instead of {rate:g}")
    else:
        say.append(f"a lidar line rate {factor:.1f} times higher")
    say += _geometry_advice(result, recipe, on_cube, factor)
    say += _certificate_advice(result, recipe)
    return "What would help (each alone): " + "; ".join(say) + "."


def _certificate_advice(result: CalibrationResult, recipe: Recipe) -> list[str]:
    """When the range offset the station measured (and no certificate gave) is what keeps the
    prediction over the budget, the lidar's certificate (:mod:`calstation.engine.
    certificate`), with what the error would be with the offset known."""
    sigma = result.sigma_range_offset
    if (result.range_offset is None or sigma is None or not math.isfinite(sigma)
            or "certificate" in result.diagnostics):
        return []
    accuracy = recipe.calibration.accuracy
    known = predict(result, accuracy, recipe.fixtures.platter, known=("range_offset",))
    if not known.max_m <= accuracy.max_error:
        return []
    return [f"the lidar's range offset from its calibration certificate "
            f"(calibration.range_offset_certificate; measured here to ± "
            f"{display.number('range_offset', sigma)}): with it known the predicted error would "
            f"be {display.number('predicted_error', known.max_m)}"]


def _fits_the_cube(recipe: Recipe) -> bool:
    """Whether the recipe's fine-tuning strategy fits the QA cube (its spin scan turns the
    cube, not the spin target)."""
    from calstation import plugins
    from calstation.errors import PluginError

    try:
        return bool(plugins.strategy(recipe.calibration.strategy).fixture == "qa_cube")
    except PluginError:  # an unknown strategy was refused long before a refusal's advice
        return False


def _bias_advice(
    result: CalibrationResult, predicted: PredictedError, recipe: Recipe, on_cube: bool
) -> str:
    """What would help when the bias bound alone is over the budget: more data cannot."""
    budget = recipe.calibration.accuracy.max_error
    head = (f"The bound on the remaining bias, {predicted.bias_m * 1e3:.3f} mm, is itself over "
            "the budget: more data cannot help.")
    if not on_cube:
        return (f"{head} Use a spin target that shows the axis tilt better (taller, "
                "off-centre) or raise calibration.accuracy.max_error.")
    noise = float(result.diagnostics.get("range_noise_m", math.nan))
    say = []
    if math.isfinite(noise) and noise > 0:
        # the cube faces' bias in ry grows with the range noise's square
        quieter = noise * math.sqrt(0.5 * budget / predicted.bias_m)
        say.append(f"a lidar with about {quieter * 1e3:.1f} mm of range noise instead of "
                   f"{noise * 1e3:.1f} mm (the bias of the cube's faces grows with its square)")
    say.append("the spin target with the periodicity strategy (calibration.strategy)")
    say.append(f"a calibration.accuracy.max_error of at least {predicted.max_m * 1e3:.2f} mm")
    return f"{head} What would help (each alone): " + "; ".join(say) + "."


def _geometry_advice(
    result: CalibrationResult, recipe: Recipe, on_cube: bool, factor: float
) -> list[str]:
    """Advice on the fixture, when the parameter that limits the accuracy is one a fixture's
    height or placement sets."""
    accuracy = recipe.calibration.accuracy
    parts = contributions(
        result.H, result.sigma, result.diagnostics.get("covariance"),
        radius=accuracy.work_radius(recipe.fixtures.platter), height=accuracy.height,
        level=accuracy.level,
    )
    if not parts:
        return []
    worst = max(parts, key=lambda n: parts[n] if math.isfinite(parts[n]) else -1.0)
    if worst != "ry":
        return []
    if on_cube:
        return ["re-seat the QA cube so that two side faces face the lidar"]
    target = recipe.fixtures.spin_target
    say = [f"a spin target {math.sqrt(factor):.1f} times taller (ry, the axis tilt out of the "
           "scan plane, limits the accuracy; a taller target's facets show it more)"]
    offset = getattr(target, "offset", (0.0, 0.0))
    if math.hypot(*offset) < 0.03:
        say.append("place the spin target about 60 mm off-centre (fixtures.spin_target.offset): "
                   "centred, its facets barely show ry")
    return say


def judge(
    result: CalibrationResult, recipe: Recipe, *, ry_failure: str | None = None,
    turns: float | None = None,
) -> tuple[CalibrationResult, list[str]]:
    """A final calibration judged as the station judges it: (``result`` with its predicted
    error recorded, every reason it is refused). The reasons: any ``calibration.max_sigma``
    limit exceeded, the cube step's ry failure (``ry_failure``), and the accuracy budget, with
    what would help. The last stage of :func:`calstation.pipeline.calibrate`, so that a
    calibration made outside a run (``calstation calibrate``, re-processing) is accepted or
    refused exactly as a run would."""
    from calstation.engine.observability import problems_with_cube

    refused = problems_with_cube(result, recipe.calibration.max_sigma, ry_failure)
    unset = range_model_unset(result)
    if unset:
        refused.append(unset)
    result, predicted = with_prediction(result, recipe, turns=turns)
    budget = budget_failure(result, predicted, recipe, scan="spin_scan",
                            turns=1.0 if turns is None else turns)
    return result, [*refused, *([budget] if budget else [])]


def with_scale_uncertainty(result: CalibrationResult, recipe: Recipe) -> CalibrationResult:
    """``result`` with the uncertainty of the lidar's scale error it did not measure
    (``calibration.range_model: offset``; ``calibration.range_scale_sigma``) in its σ and
    covariance (:func:`calstation.engine.rangemodel.with_unmeasured_scale`), recorded as
    ``diagnostics["unmeasured_scale_sigma"]``; once only, and only for a result whose range
    offset was measured (a spin target's alone, which holds it, is not judged on the range
    model) and which has no scale of its own."""
    sigma_scale = recipe.calibration.range_scale_sigma
    offset_sigma = result.sigma_range_offset
    if (result.range_offset is None or result.range_scale is not None or sigma_scale <= 0
            or offset_sigma is None or not math.isfinite(offset_sigma)
            or "unmeasured_scale_sigma" in result.diagnostics):
        return result
    sigma, covariance = with_unmeasured_scale(
        result.H.t, result.sigma, result.diagnostics.get("covariance"), sigma_scale)
    diagnostics = {**result.diagnostics, "unmeasured_scale_sigma": sigma_scale}
    if covariance is not None:
        diagnostics["covariance"] = covariance
    return replace(result, sigma=sigma, diagnostics=diagnostics)


def range_model_unset(result: CalibrationResult) -> str | None:
    """Why ``result`` cannot be accepted when the recipe's range model (DESIGN §9) was not set
    by a scan that sees it: a range term held at its start, without a σ of its own (a spin
    target alone cannot tell the lidar's range offset from its distance), else None."""
    unset = [name for name, value, sigma in (
        ("range offset", result.range_offset, result.sigma_range_offset),
        ("range scale error", result.range_scale, result.sigma_range_scale),
        ("incidence bias", result.incidence_bias, result.sigma_incidence_bias),
    ) if value is not None and not (sigma is not None and math.isfinite(sigma))]
    if not unset or "disagreement" in result.diagnostics.get("joint", {}):
        return None  # the cube was scanned, and why it could not set them is said
    return (f"the lidar's {' and '.join(unset)} (calibration.range_model) were not measured: "
            "the spin target alone cannot tell them from where the lidar stands, so H would "
            "hold them. Scan the QA cube too (its known size and square faces set them), or set "
            "calibration.range_model: none for a lidar without a range error")
