"""The operator page's end screen: what a run found, every value beside its limit.

Built from :func:`calstation.storage.report_html.report_data` (what the report shows), plus what
an operator needs at a glance: the unit serial, the drift of each parameter beside its limit,
each step's time and the run's elapsed time, and which calibration values were not estimated.
"""

from __future__ import annotations

import datetime as dt
import math
from typing import Any

from calstation.station.operator import step_title

STAGES = {"initial": "initial, from the L-target", "fine": "fine-tuned",
          "reprocess": "re-processed"}
"""How the calibrations' stages read on the end screen."""


def end_screen(data: dict[str, Any]) -> dict[str, Any]:
    """The end screen's data from ``report_data(…, views=False)``."""
    run = data["run"]
    return {
        **{k: data[k] for k in ("verdict", "cube_rows", "serial", "accuracy")},
        "error": run["error"], "status": run["status"],
        "calibrations": [_calibration(c) for c in data["calibrations"]],
        "drift": _drift(data.get("drift"), data.get("qa")),
        "steps": [{"name": s["name"], "title": step_title(s["name"]), "attempt": s["attempt"],
                   "status": s["status"], "seconds": s.get("duration_s")}
                  for s in data["steps"]],
        "elapsed_s": _seconds(run.get("started_at"), run.get("finished_at")),
    }


def _calibration(c: dict[str, Any]) -> dict[str, Any]:
    """A calibration row: its label, and which values were not estimated (no σ and held at
    0: rx, the turntable's gauge, and the initial calibration's ry)."""
    not_estimated = [p for p, v in c["values"].items()
                     if c["sigma"].get(p) is None and (v is None or v == 0.0)]
    label = STAGES.get(c["stage"], c["stage"])
    if c.get("strategy") and c["stage"] != "initial":
        label += f" ({c['strategy']})"
    return {**c, "label": label, "not_estimated": not_estimated}


def _drift(drift: dict[str, Any] | None, qa: dict[str, Any] | None) -> dict[str, Any] | None:
    """Each parameter's change since the previous accepted calibration, beside its limit."""
    if not drift or not qa:
        return None
    rows = []
    for p, delta in (drift.get("delta") or {}).items():
        if delta is None:
            continue
        if p.startswith("t"):
            value, limit, unit = 1e3 * float(delta), 1e3 * float(qa["drift_translation"]), "mm"
        else:
            value, limit, unit = math.degrees(float(delta)), float(qa["drift_rotation_deg"]), "°"
        rows.append({"name": p, "value": value, "limit": limit, "unit": unit,
                     "ok": p not in drift.get("flagged", [])})
    return {"previous_run": drift.get("previous_run"), "rows": rows,
            "flagged": list(drift.get("flagged", [])), "fails": bool(qa.get("drift_fails"))}


def _seconds(start: str | None, end: str | None) -> float | None:
    if not start or not end:
        return None
    return (dt.datetime.fromisoformat(end) - dt.datetime.fromisoformat(start)).total_seconds()
