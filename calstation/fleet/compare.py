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
from collections.abc import Iterable, Mapping
from typing import SupportsFloat, TypedDict

from calstation.engine.accuracy import true_distortion
from calstation.engine.frames import Extrinsics
from calstation.engine.result import CalibrationResult
from calstation.jsonvalue import JSONValue
from calstation.recipes import Recipe
from calstation.storage.db import PARAMS, Calibration, CubeCheckRecord

CUBE_FIGURES = ("edge_error", "obb_error", "flatness_rms", "perpendicularity_deg", "twist_deg")
"""The cube check's figures compared (metres; the angles in degrees)."""


def work_volume(recipe: Recipe) -> tuple[float, float]:
    """(radius, height) of the recipe's work volume, metres (``calibration.accuracy``: its
    radius, by default the platter's, and its height, by default 0.15 m)."""
    accuracy = recipe.calibration.accuracy
    return accuracy.work_radius(recipe.fixtures.platter), accuracy.height


class StoredCalibration(TypedDict, total=False):
    """A stored calibration as :func:`compare` takes it (empty for a run without one)."""

    calibration_id: int
    stage: str
    strategy: str
    gauge: JSONValue
    H: dict[str, float]
    sigma: dict[str, float | None]
    result: CalibrationResult


class CubeFigures(TypedDict):
    """The figures of a cube check (:func:`cube_figures`; metres, the angles in degrees)."""

    edge_error: float | None
    obb_error: float | None
    flatness_rms: float | None
    perpendicularity_deg: float | None
    twist_deg: float | None
    passed: bool
    failures: list[str]


def _finite(value: object) -> float | None:
    if value is None:
        return None
    if not isinstance(value, SupportsFloat | str):
        raise TypeError(f"not a number: {value!r}")
    return float(value) if math.isfinite(float(value)) else None


def _field(check: object, key: str) -> object:
    """``key`` of a mapping, else the attribute ``key`` (None when it has none)."""
    return check.get(key) if isinstance(check, dict) else getattr(check, key, None)


def stored_calibration(c: Calibration) -> StoredCalibration:
    """A stored calibration as :func:`compare` takes it: id, stage, strategy, gauge, H, σ (None
    where not estimated), and the whole of it as the engine's result (``result``)."""
    diagnostics = c.diagnostics or {}
    return {"calibration_id": c.id, "stage": c.stage, "strategy": c.strategy,
            "gauge": diagnostics.get("gauge"), "H": c.params(), "sigma": c.sigmas(),
            "result": c.result()}


def cube_figures(check: CubeCheckRecord | Mapping[str, object] | object | None
                 ) -> CubeFigures | None:
    """The figures of a cube check (a stored row, a mapping, or the engine's check), with
    ``passed`` and ``failures``; None without a check."""
    if check is None:
        return None
    failures = _field(check, "failures") or []
    if not isinstance(failures, Iterable):
        raise TypeError(f"not a list of failures: {failures!r}")
    return {"edge_error": _finite(_field(check, "edge_error")),
            "obb_error": _finite(_field(check, "obb_error")),
            "flatness_rms": _finite(_field(check, "flatness_rms")),
            "perpendicularity_deg": _finite(_field(check, "perpendicularity_deg")),
            "twist_deg": _finite(_field(check, "twist_deg")),
            "passed": bool(_field(check, "passed")),
            "failures": [str(f) for f in failures]}


def predicted(result: CalibrationResult | None, recipe: Recipe) -> float | None:
    """The predicted reconstruction error (m) of a calibration over the recipe's work volume,
    as the station predicts it (:func:`calstation.engine.observability.predict`: the covariance,
    or the σ, and any bound on a remaining bias), None when it has no σ (or there is none)."""
    from calstation.engine.observability import predict

    if result is None:
        return None
    return _finite(predict(result, recipe.calibration.accuracy, recipe.fixtures.platter).max_m)


def _values(figures: CubeFigures | None) -> dict[str, float | None]:
    """The figures of :data:`CUBE_FIGURES` of a cube check; none without one."""
    if figures is None:
        return {}
    return {"edge_error": figures["edge_error"], "obb_error": figures["obb_error"],
            "flatness_rms": figures["flatness_rms"],
            "perpendicularity_deg": figures["perpendicularity_deg"],
            "twist_deg": figures["twist_deg"]}


def compare(
    stored: StoredCalibration,
    new: CalibrationResult,
    refused: list[str],
    recipe: Recipe,
    stored_cube: CubeFigures | None = None,
    new_cube: CubeFigures | None = None,
) -> dict[str, object]:
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
        was, now = _values(stored_cube), _values(new_cube)
        change = {k: (None if (x := was.get(k)) is None or (y := now.get(k)) is None
                      else y - x) for k in CUBE_FIGURES}
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
