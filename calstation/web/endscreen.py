"""The operator page's end screen: what a run found, every value beside its limit.

Built from :func:`calstation.storage.report_html.report_data` (what the report shows), plus what
an operator needs at a glance: the unit serial, the drift of each parameter beside its limit,
each step's time and the run's elapsed time, and which calibration values were not estimated.
Values stay in their stored units; the page formats them (:mod:`calstation.display`).
"""

from __future__ import annotations

from typing import Any

from calstation import display

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
        "steps": [{"name": s["name"], "title": display.step_title(s["name"]),
                   "attempt": s["attempt"], "status": s["status"],
                   "seconds": s.get("duration_s")}
                  for s in data["steps"]],
        "started_at": run.get("started_at"), "finished_at": run.get("finished_at"),
        "elapsed_s": display.seconds_between(run.get("started_at"), run.get("finished_at")),
    }


def _calibration(c: dict[str, Any]) -> dict[str, Any]:
    """A calibration row with its label."""
    label = STAGES.get(c["stage"], c["stage"])
    if c.get("strategy") and c["stage"] != "initial":
        label += f" ({c['strategy']})"
    return {**c, "label": label}


def _drift(drift: dict[str, Any] | None, qa: dict[str, Any] | None) -> dict[str, Any] | None:
    """Each parameter's change since the previous accepted calibration, beside its limit
    (stored units: m, rad)."""
    if not drift or not qa:
        return None
    import math

    rows = []
    for p, delta in (drift.get("delta") or {}).items():
        if delta is None:
            continue
        limit = (float(qa["drift_translation"]) if p.startswith("t")
                 else math.radians(float(qa["drift_rotation_deg"])))
        rows.append({"name": p, "value": float(delta), "limit": limit,
                     "unit": display.quantity(p).stored,
                     "ok": p not in drift.get("flagged", [])})
    return {"previous_run": drift.get("previous_run"), "rows": rows,
            "flagged": list(drift.get("flagged", [])), "fails": bool(qa.get("drift_fails"))}
