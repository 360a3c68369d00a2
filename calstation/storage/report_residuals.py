"""The report's view of the lidar's range errors its range model does not hold: the cube range
fit's residuals against range, incidence angle and azimuth
(:mod:`calstation.engine.residuals`), read back from a stored calibration, said in words and
drawn."""

from __future__ import annotations

from typing import cast

from calstation.engine.residuals import TrendRecord
from calstation.jsonvalue import JSONObject, JSONValue
from calstation.storage.report_types import Figure

RESIDUAL_AXES = (("range", "range (m)"), ("incidence", "incidence angle (°)"),
                 ("azimuth", "azimuth (°)"))
"""The quantities the cube's range residuals are shown against, with their axis titles."""


def range_residuals_of(joint: JSONValue) -> dict[str, TrendRecord] | None:
    """The cube's range-fit residual trends in a calibration's stored ``diagnostics["joint"]``
    (:func:`calstation.engine.residuals.residual_trends`), or None."""
    cube = joint.get("cube") if isinstance(joint, dict) else None
    residuals = cube.get("residuals") if isinstance(cube, dict) else None
    keys = set(TrendRecord.__annotations__)
    if not isinstance(residuals, dict) or not residuals or not all(
            isinstance(t, dict) and keys <= set(t) for t in residuals.values()):
        return None
    # stored by the engine as residual_trends gave it, every key checked above
    return cast("dict[str, TrendRecord]", residuals)


def range_residuals_text(residuals: dict[str, TrendRecord]) -> str:
    """What the cube's range residuals say, in words: the errors the lidar's range model does
    not hold, or that they show none."""
    from calstation.engine.residuals import unmodelled

    seen = unmodelled(residuals)
    if not seen:
        return ("The cube's faces show no range error the lidar's range model does not hold: "
                "their residuals show no trend against range, incidence angle or azimuth.")
    return ("The cube's faces show a range error the lidar's range model does not hold: "
            + "; ".join(seen) + ".")


def range_residuals_figure(residuals: dict[str, TrendRecord]) -> Figure:
    """The cube's range residuals (median of each bin and its σ, mm; positive reads long)
    against range, incidence angle and azimuth, side by side."""
    traces: list[JSONObject] = []
    layout: JSONObject = {}
    shown = [(name, title) for name, title in RESIDUAL_AXES if name in residuals]
    for k, (name, title) in enumerate(shown, start=1):
        t = residuals[name]
        axis = "" if k == 1 else str(k)
        traces.append({
            "type": "scatter", "mode": "markers+lines", "name": name,
            "x": [round(float(c), 4) for c in t["centre"]],
            "y": [round(float(m) * 1e3, 4) for m in t["median_m"]],
            "error_y": {"type": "data", "array": [round(3 * float(e) * 1e3, 4)
                                                  for e in t["sigma_m"]]},
            "marker": {"color": "#c0392b" if t.get("significant") else "#2c3e50"},
            "xaxis": f"x{axis}", "yaxis": f"y{axis}",
        })
        layout[f"xaxis{axis}"] = {"title": {"text": title}}
        layout[f"yaxis{axis}"] = {"title": {"text": "range error (mm)" if k == 1 else ""}}
    grid: JSONObject = {"rows": 1, "columns": len(shown), "pattern": "independent"}
    layout.update({
        "height": 300, "showlegend": False, "margin": {"l": 60, "r": 20, "t": 40, "b": 50},
        "title": {"text": "the cube's range residuals (median ± 3σ; positive reads long)"},
        "grid": grid,
    })
    return {"data": traces, "layout": layout}
