"""What a finished task records: an estimate as plain numbers, its errors against the
simulator's truth, and whether it converged; every record is JSON-ready."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, TypedDict

from calstation.engine.frames import PARAMETER_NAMES, Extrinsics
from calstation.jsonvalue import JSONObject, JSONValue

if TYPE_CHECKING:
    from calstation.engine.result import CalibrationResult

Measured = dict[str, float | str]
"""Measurements by name, or ``{"failed": message}`` when they could not be made."""


class LandscapeSpec(TypedDict, total=False):
    """What a landscape task samples (``Task.landscape``), or a basin task's start group."""

    method: str
    pair_name: str
    pair: list[str]
    row: int
    offsets: list[float]
    centre: list[float]
    truth: list[float]
    group: str
    level: int


class LandscapeRow(TypedDict):
    """One sampled row of a cost landscape: the costs (None where not evaluated) along ``v`` at
    ``u[row]``, the axes and the truth in display units (mm, °)."""

    method: str
    pair_name: str
    pair: list[str]
    row: int
    u: list[float]
    v: list[float]
    costs: list[float | None]
    truth: list[float]
    source: str


class LandscapeGrid(TypedDict):
    """A whole landscape of one method, from its rows: ``cost[i][j]`` at ``u[i]``, ``v[j]``
    (NaN where not evaluated), the truth's place, the scenario, the pair and the cost's source."""

    u: list[float]
    v: list[float]
    cost: list[list[float]]
    truth: list[float] | None
    scenario: str
    pair: list[str]
    source: str


class BenchRecord(TypedDict, total=False):
    """One finished task (:func:`calstation.bench.worker.run_task`), as ``records.jsonl`` keeps
    it: which task, its status, and what its kind measured. A number that is not finite is
    written as null (NaN) or ±1e308 (:func:`_jsonable`)."""

    id: str
    kind: str
    scenario: str
    method: str
    set: str
    index: int
    variant: str
    group: str
    level: int
    status: str  # "ok" | "failed"
    error_message: str
    traceback: str
    wall_s: float
    converged: bool
    stage_s: float
    start: dict[str, float]
    # the estimate (result_fields)
    H: dict[str, float]
    sigma: dict[str, float]
    cost: float
    iterations: int
    strategy: str
    timings: dict[str, float]
    diagnostics: JSONValue
    # against the truth (against_truth, _evaluate)
    truth: dict[str, float]
    error: dict[str, float]
    axis: Measured
    cube: JSONObject
    truth_cube: JSONObject
    distortion: Measured
    eval_timings: dict[str, float]
    landscape: LandscapeRow


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


def scan_of(strategy: object) -> str:
    """Which of a scenario's scans ("spin" or "cube") a fine-tuning strategy runs on."""
    return "cube" if getattr(strategy, "fixture", "spin_target") == "qa_cube" else "spin"


def against_truth(H: Extrinsics, truth: Extrinsics) -> BenchRecord:
    """An estimate's per-parameter errors and axis errors against the truth (the axis errors as
    ``{"failed": message}`` if they cannot be computed)."""
    axis: Measured
    try:
        from calstation.engine.metrics import axis_errors

        axis = {k: float(v) for k, v in axis_errors(H, truth).items()}
    except Exception as exc:
        axis = {"failed": f"{type(exc).__name__}: {exc}"}
    return {
        "truth": _h_dict(truth),
        "error": {n: float(getattr(H, n) - getattr(truth, n)) for n in PARAMETER_NAMES},
        "axis": axis,
    }


def _jsonable(x: object) -> JSONValue:
    """Nested data with numpy scalars/arrays turned into plain JSON types."""
    import numpy as np

    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, np.generic):
        item: JSONValue = x.item()  # a Python scalar, kept as it is
        return item
    if isinstance(x, float) and not math.isfinite(x):
        return None if math.isnan(x) else (1e308 if x > 0 else -1e308)
    if isinstance(x, str | int | float | bool) or x is None:
        return x
    return str(x)


def converged(method: str, record: BenchRecord) -> bool:
    """Whether a record meets :data:`CONVERGENCE` for its method (False if it failed)."""
    if record.get("status") != "ok":
        return False
    limits = CONVERGENCE.get(method if method in CONVERGENCE else "shape", {})
    for key, limit in limits.items():
        value: float | str | None
        if key.startswith("axis_"):
            value = record["axis"].get(key)
        else:
            value = record["error"].get(key.rsplit("_", 1)[0])
        if value is None or not abs(float(value)) <= limit:
            return False
    return True


def result_fields(result: CalibrationResult) -> BenchRecord:
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


def _small_diagnostics(diag: Mapping[str, object]) -> dict[str, object]:
    """Diagnostics without bulky arrays (keep scalars, short lists)."""
    out: dict[str, object] = {}
    for k, v in diag.items():
        if isinstance(v, str | int | float | bool) or v is None:
            out[k] = v
        elif isinstance(v, list | tuple) and len(v) <= 64:
            out[k] = list(v)
        elif hasattr(v, "shape") and getattr(v, "size", 1e9) <= 64:
            out[k] = v
    return out
