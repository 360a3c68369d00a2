"""The operator page's end screen: what a run found, every value beside its limit.

Built from :func:`calstation.storage.report_html.report_data` (what the report shows), plus what
an operator needs at a glance: the unit serial, the drift of each parameter beside its limit,
each step's time and the run's elapsed time, and which calibration values were not estimated.
Values stay in their stored units; the page formats them (:mod:`calstation.display`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, TypedDict

from calstation import display
from calstation.jsonvalue import JSONObject
from calstation.storage.report import json_float

if TYPE_CHECKING:
    from calstation.storage.report_types import Accuracy, CalibrationRow, CubeRow, ReportData

STAGES = {"initial": "initial, from the L-target", "fine": "fine-tuned",
          "reprocess": "re-processed"}
"""How the calibrations' stages read on the end screen."""


class EndStep(TypedDict):
    """A step attempt as the end screen lists it."""

    name: str
    title: str
    attempt: int
    status: str
    seconds: float | None


class EndScreen(TypedDict):
    """What the operator page's end screen shows (:func:`end_screen`)."""

    verdict: str
    cube_rows: list[CubeRow]
    serial: str | None
    accuracy: Accuracy | None
    error: str | None
    status: str
    calibrations: list[dict[str, object]]
    drift: dict[str, object] | None
    steps: list[EndStep]
    started_at: str | None
    finished_at: str | None
    elapsed_s: float | None


def end_screen(data: ReportData) -> EndScreen:
    """The end screen's data from ``report_data(…, views=False)``."""
    run = data["run"]
    return {
        "verdict": data["verdict"], "cube_rows": data["cube_rows"], "serial": data["serial"],
        "accuracy": data["accuracy"],
        "error": run["error"], "status": run["status"],
        "calibrations": [_calibration(c) for c in data["calibrations"]],
        "drift": _drift(data["drift"], data["qa"]),
        "steps": [{"name": s["name"], "title": display.step_title(s["name"]),
                   "attempt": s["attempt"], "status": s["status"],
                   "seconds": s["duration_s"]}
                  for s in data["steps"]],
        "started_at": run["started_at"], "finished_at": run["finished_at"],
        "elapsed_s": display.seconds_between(run["started_at"], run["finished_at"]),
    }


def _calibration(c: CalibrationRow) -> dict[str, object]:
    """A calibration row with its label."""
    label = STAGES.get(c["stage"], c["stage"])
    if c["strategy"] and c["stage"] != "initial":
        label += f" ({c['strategy']})"
    return {**c, "label": label}


def _drift(drift: JSONObject | None, qa: JSONObject | None) -> dict[str, object] | None:
    """Each parameter's change since the previous accepted calibration, beside its limit
    (stored units: m, rad)."""
    if not drift or not qa:
        return None
    import math

    delta_of = drift.get("delta") or {}
    flagged = drift.get("flagged", [])
    if not isinstance(delta_of, dict) or not isinstance(flagged, list):
        raise TypeError(f"not a stored drift: {drift!r}")
    rows = []
    for p, delta in delta_of.items():
        if delta is None:
            continue
        limit = (json_float(qa["drift_translation"]) if p.startswith("t")
                 else math.radians(json_float(qa["drift_rotation_deg"])))
        rows.append({"name": p, "value": json_float(delta), "limit": limit,
                     "unit": display.quantity(p).stored,
                     "ok": p not in flagged})
    return {"previous_run": drift.get("previous_run"), "rows": rows,
            "flagged": list(flagged), "fails": bool(qa.get("drift_fails"))}
