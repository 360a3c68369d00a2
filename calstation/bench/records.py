"""What a finished task records: an estimate as plain numbers, its errors against the
simulator's truth, and whether it converged; every record is JSON-ready."""

from __future__ import annotations

import math
from typing import Any

from calstation.engine.frames import PARAMETER_NAMES, Extrinsics

CONVERGENCE: dict[str, dict[str, float]] = {
    # the engine issue's acceptance thresholds (DESIGN §8 metrics against the true H)
    "periodicity": {
        "axis_offset_m": 0.5e-3,
        "axis_angle_rad": math.radians(0.1),
        "rz_rad": math.radians(0.05),
    },
    "shape": {"axis_offset_m": 2.0e-3, "axis_angle_rad": math.radians(0.3)},
    # the initial calibration must land inside the paper's set-A box around the truth
    "initial": {
        "tx_m": 0.100,
        "ty_m": 0.100,
        "tz_m": 0.100,
        "ry_rad": math.radians(1.0),
        "rz_rad": math.radians(1.0),
    },
}
"""Per method, the largest error still counted as converged (metres / radians)."""


def _h_dict(h: Extrinsics) -> dict[str, float]:
    return {n: float(getattr(h, n)) for n in PARAMETER_NAMES}


def scan_of(strategy: Any) -> str:
    """Which of a scenario's scans ("spin" or "cube") a fine-tuning strategy runs on."""
    return "cube" if getattr(strategy, "fixture", "spin_target") == "qa_cube" else "spin"


def against_truth(H: Extrinsics, truth: Extrinsics) -> dict[str, Any]:
    """An estimate's per-parameter errors and axis errors against the truth (the axis errors as
    ``{"failed": message}`` if they cannot be computed)."""
    out: dict[str, Any] = {
        "truth": _h_dict(truth),
        "error": {n: float(getattr(H, n) - getattr(truth, n)) for n in PARAMETER_NAMES},
    }
    try:
        from calstation.engine.metrics import axis_errors

        out["axis"] = {k: float(v) for k, v in axis_errors(H, truth).items()}
    except Exception as exc:
        out["axis"] = {"failed": f"{type(exc).__name__}: {exc}"}
    return out


def _jsonable(x: Any) -> Any:
    """Nested data with numpy scalars/arrays turned into plain JSON types."""
    import numpy as np

    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None if math.isnan(x) else (1e308 if x > 0 else -1e308)
    if isinstance(x, str | int | float | bool) or x is None:
        return x
    return str(x)


def converged(method: str, record: dict[str, Any]) -> bool:
    """Whether a record meets :data:`CONVERGENCE` for its method (False if it failed)."""
    if record.get("status") != "ok":
        return False
    limits = CONVERGENCE.get(method if method in CONVERGENCE else "shape", {})
    for key, limit in limits.items():
        if key.startswith("axis_"):
            value = record["axis"].get(key)
        else:
            value = record["error"].get(key.rsplit("_", 1)[0])
        if value is None or not abs(float(value)) <= limit:
            return False
    return True


def result_fields(result: Any) -> dict[str, Any]:
    """A :class:`~calstation.engine.result.CalibrationResult` as a record's fields: H, σ, cost,
    iterations, strategy, timings and the small diagnostics."""
    return {
        "H": _h_dict(result.H),
        "sigma": {k: float(v) for k, v in dict(result.sigma).items()},
        "cost": float(result.cost),
        "iterations": int(result.iterations),
        "strategy": str(result.strategy),
        "timings": {k: float(v) for k, v in dict(result.timings).items()},
        "diagnostics": _jsonable(_small_diagnostics(dict(result.diagnostics))),
    }


def _small_diagnostics(diag: dict[str, Any]) -> dict[str, Any]:
    """Diagnostics without bulky arrays (keep scalars, short lists)."""
    out: dict[str, Any] = {}
    for k, v in diag.items():
        if isinstance(v, str | int | float | bool) or v is None:
            out[k] = v
        elif isinstance(v, list | tuple) and len(v) <= 64:
            out[k] = list(v)
        elif hasattr(v, "shape") and getattr(v, "size", 1e9) <= 64:
            out[k] = v
    return out
