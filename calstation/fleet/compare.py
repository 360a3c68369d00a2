"""A stored H against the one today's engine finds: each parameter, the work volume, the
predicted reconstruction error, the verdict, and the cube re-measured under the new H.

The work volume is where the station's users put objects: the cylinder on the platter of the
recipe's accuracy budget (``calibration.accuracy``, :func:`work_volume`). The change *in the
work volume* is how far the volume's points, seen under the stored H and reconstructed with the
new one, move after the best rigid alignment
(:func:`calstation.engine.accuracy.true_distortion`): what a unit calibrated with the stored H
gets wrong by, if the new H is right. The *predicted error* is the accuracy budget's figure
(:func:`calstation.engine.observability.predict`, at the budget's level) of each calibration's
own σ, covariance and bias bound over the same volume.

Values are JSON-ready, in stored units (metres, radians; the cube's angles in degrees), None
where a figure does not exist (a σ that was not estimated, a run without a cube scan).
"""

from __future__ import annotations

import math
from typing import Any

from calstation.engine.accuracy import true_distortion
from calstation.engine.frames import Extrinsics
from calstation.engine.result import CalibrationResult
from calstation.recipes import Recipe
from calstation.storage.db import PARAMS, Calibration, CubeCheckRecord

CUBE_FIGURES = ("edge_error", "obb_error", "flatness_rms", "perpendicularity_deg", "twist_deg")
"""The cube check's figures compared (metres; the angles in degrees)."""


def work_volume(recipe: Recipe) -> tuple[float, float]:
    """(radius, height) of the recipe's work volume, metres (``calibration.accuracy``: its
    radius, by default the platter's, and its height, by default 0.15 m)."""
    accuracy = recipe.calibration.accuracy
    return accuracy.work_radius(recipe.fixtures.platter), accuracy.height


def _finite(value: Any) -> float | None:
    return float(value) if value is not None and math.isfinite(float(value)) else None


def stored_calibration(c: Calibration) -> dict[str, Any]:
    """A stored calibration as :func:`compare` takes it: id, stage, strategy, gauge, H, σ (None
    where not estimated), and the whole of it as the engine's result (``result``)."""
    diagnostics = c.diagnostics or {}
    return {"calibration_id": c.id, "stage": c.stage, "strategy": c.strategy,
            "gauge": diagnostics.get("gauge"), "H": c.params(), "sigma": c.sigmas(),
            "result": c.result()}


def cube_figures(check: CubeCheckRecord | dict[str, Any] | Any | None) -> dict[str, Any] | None:
    """The figures of a cube check (a stored row, a mapping, or the engine's check), with
    ``passed`` and ``failures``; None without a check."""
    if check is None:
        return None
    get = check.get if isinstance(check, dict) else (lambda k: getattr(check, k, None))
    out: dict[str, Any] = {k: _finite(get(k)) for k in CUBE_FIGURES}
    out["passed"] = bool(get("passed"))
    out["failures"] = [str(f) for f in (get("failures") or [])]
    return out


def predicted(result: CalibrationResult | None, recipe: Recipe) -> float | None:
    """The predicted reconstruction error (m) of a calibration over the recipe's work volume,
    as the station predicts it (:func:`calstation.engine.observability.predict`: the covariance,
    or the σ, and any bound on a remaining bias), None when it has no σ (or there is none)."""
    from calstation.engine.observability import predict

    if result is None:
        return None
    return _finite(predict(result, recipe.calibration.accuracy, recipe.fixtures.platter).max_m)


def compare(
    stored: dict[str, Any],
    new: CalibrationResult,
    refused: list[str],
    recipe: Recipe,
    stored_cube: dict[str, Any] | None = None,
    new_cube: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The stored calibration (:func:`stored_calibration`) against ``new`` (today's result,
    refused for ``refused``); the run's stored cube figures against those re-measured under the
    new H (:func:`cube_figures`). See the module docstring."""
    radius, height = work_volume(recipe)
    new_H = new.H.as_dict()
    difference = {p: new_H[p] - float(stored["H"][p]) for p in PARAMS}
    moved = true_distortion(new.H, Extrinsics.from_dict(stored["H"]), radius=radius,
                            height=height)["max_m"]
    before = predicted(stored.get("result"), recipe)
    after = predicted(new, recipe)
    gauge = new.diagnostics.get("gauge")
    cube = None
    if stored_cube is not None or new_cube is not None:
        change = {k: (None if stored_cube is None or new_cube is None
                      or stored_cube.get(k) is None or new_cube.get(k) is None
                      else new_cube[k] - stored_cube[k]) for k in CUBE_FIGURES}
        cube = {"stored": stored_cube, "new": new_cube, "change": change}
    return {
        "stored": {k: stored.get(k) for k in ("calibration_id", "stage", "strategy", "gauge",
                                              "H", "sigma")},
        "new": {"strategy": new.strategy, "gauge": gauge, "H": new_H,
                "sigma": {p: _finite(v) for p, v in new.sigma.items()},
                "cost": _finite(new.cost)},
        "difference": difference,
        "gauges_differ": (stored.get("gauge") or None) != (gauge or None),
        "work_volume": {"radius_m": radius, "height_m": height},
        "change_in_work_volume_m": _finite(moved),
        "predicted_error": {"stored_m": before, "new_m": after,
                            "change_m": None if before is None or after is None
                            else after - before},
        "accepted": not refused,
        "refused": list(refused),
        "cube": cube,
        "drift_limits": {"translation_m": recipe.qa.drift_translation,
                         "rotation_deg": recipe.qa.drift_rotation_deg},
    }
