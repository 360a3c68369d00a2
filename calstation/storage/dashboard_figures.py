"""The QA dashboard's plotly figures (plain JSON) from :func:`.dashboard.dashboard`'s data.

Every point and bar carries the link to its runs in ``customdata`` (a run's page, or the
history filtered to the runs behind it); the page's script follows it on a click.
"""

from __future__ import annotations

from urllib.parse import urlencode

from calstation import display
from calstation.storage.dashboard_types import (
    Chart,
    ComparisonRow,
    DashboardData,
    Figure,
    YieldRow,
)
from calstation.storage.db import RunStatus

COLOURS = ("#0969da", "#bc4c00", "#1a7f37", "#8250df", "#bf3989", "#57606a")
FLAG = "#cf222e"
ABORTED = "#9a6700"


def history_link(**filters: str | None) -> str:
    """The history page filtered by ``filters`` (empty ones left out)."""
    return "/runs?" + urlencode({k: v for k, v in filters.items() if v not in (None, "")})


def _layout(title: str, y: str, height: int = 320, **extra: object) -> dict[str, object]:
    return {"title": {"text": title, "x": 0.01, "font": {"size": 15}}, "height": height,
            "margin": {"l": 70, "r": 20, "t": 44, "b": 70},
            "yaxis": {"title": {"text": y}, "automargin": True},
            "xaxis": {"automargin": True}, "legend": {"orientation": "h", "y": -0.25},
            "hovermode": "closest", **extra}


def yield_figure(data: DashboardData) -> Figure:
    """Yield and first-pass yield per station and period (click: that period's runs)."""
    traces = []
    by_station: dict[str, list[YieldRow]] = {}
    for row in data["yields"]:
        if row["period"] != "all":
            by_station.setdefault(row["station"], []).append(row)
    for i, (station, rows) in enumerate(sorted(by_station.items())):
        colour = COLOURS[i % len(COLOURS)]
        links = [history_link(station=station, since=r["since"], until=r["until"])
                 for r in rows]
        for share, name, dash in (([r["yield"] for r in rows], "yield", "solid"),
                                  ([r["first_pass_yield"] for r in rows], "first-pass yield",
                                   "dot")):
            traces.append({
                "type": "scatter", "mode": "lines+markers", "name": f"{station} {name}",
                "x": [r["period"] for r in rows],
                "y": [None if y is None else round(100 * y, 2) for y in share],
                "customdata": links, "line": {"color": colour, "dash": dash},
                "hovertemplate": f"{station} {name} %{{x}}: %{{y:.1f}} %<extra></extra>"})
    return {"data": traces, "layout": _layout(
        "yield and first-pass yield by station", "% of finished runs", yaxis={
            "title": {"text": "% of finished runs"}, "range": [0, 101]},
        xaxis={"type": "category", "title": {"text": data["period"]["group"]}})}


def cycle_figure(data: DashboardData) -> Figure:
    """Median cycle time per station and period (click: that period's runs)."""
    traces = []
    by_station: dict[str, list[YieldRow]] = {}
    for row in data["yields"]:
        if row["period"] != "all":
            by_station.setdefault(row["station"], []).append(row)
    for i, (station, rows) in enumerate(sorted(by_station.items())):
        traces.append({
            "type": "bar", "name": station, "x": [r["period"] for r in rows],
            "y": [None if r["median_cycle_s"] is None else round(r["median_cycle_s"] / 60, 2)
                  for r in rows],
            "customdata": [history_link(station=station, since=r["since"], until=r["until"])
                           for r in rows],
            "marker": {"color": COLOURS[i % len(COLOURS)]},
            "hovertemplate": f"{station} %{{x}}: median %{{y:.1f}} min<extra></extra>"})
    return {"data": traces, "layout": _layout(
        "median cycle time", "minutes", barmode="group",
        xaxis={"type": "category", "title": {"text": data["period"]["group"]}})}


def pareto_figure(data: DashboardData) -> Figure:
    """Failed and aborted runs by step and reason, most frequent first, with the cumulative
    share (click: the runs behind a bar). A run the operator aborted is no failure of the
    unit: its bar is the colour of an abort, not of a failure."""
    rows = data["pareto"]
    period = data["period"]
    links = [history_link(status=r["status"], failed_step=r["step"],
                          reason="" if r["limit"] == "aborted" else r["limit"],
                          since=period["since"], until=period["until"]) for r in rows]
    labels = [f"{r['step']}<br>{'aborted' if r['status'] == RunStatus.ABORTED else r['limit']}"
              for r in rows]
    return {"data": [
        {"type": "bar", "name": "runs", "x": labels, "y": [r["count"] for r in rows],
         "customdata": links,
         "marker": {"color": [ABORTED if r["status"] == RunStatus.ABORTED else FLAG
                              for r in rows]},
         "text": ["aborted by the operator" if r["status"] == RunStatus.ABORTED else "failed"
                  for r in rows],
         "hovertemplate": "%{x}<br>%{y} runs, %{text}<extra></extra>"},
        {"type": "scatter", "mode": "lines+markers", "name": "cumulative %", "x": labels,
         "y": [round(100 * r["cumulative"], 1) for r in rows], "yaxis": "y2",
         "customdata": links, "line": {"color": "#57606a"},
         "hovertemplate": "cumulative %{y:.0f} %<extra></extra>"},
    ], "layout": _layout(
        "failed (red) and aborted (amber) runs by step and reason, all stations", "runs",
        height=380, margin={"l": 70, "r": 60, "t": 44, "b": 90},
        xaxis={"type": "category", "tickangle": 0, "automargin": True},
        yaxis2={"overlaying": "y", "side": "right", "range": [0, 101],
                "tickmode": "array", "tickvals": [0, 25, 50, 75, 100], "ticksuffix": " %",
                "showgrid": False, "title": {"text": "cumulative share"}})}


def control_figure(c: Chart) -> Figure:
    """A control chart: the points (out-of-control ones in red, with their rules), the
    centre line, ±3σ, and the recipe's limit (click a point: its run), in the unit shown.
    The chart is scaled to the points and their control limits: a recipe limit far outside
    them is named in the title rather than drawn, so the points never collapse into a line."""
    pts, lim = c["points"], c["limits"]
    q = display.quantity(c["param"])
    if not pts or lim is None:
        return {"data": [], "layout": _layout(f"{c['label']} — no value", c["short"])}
    k = q.factor
    xs = [p["t"] for p in pts]
    values = [p["value"] * k for p in pts]
    bad = [(p, v) for p, v in zip(pts, values, strict=True) if p["rules"]]
    hover = f"run %{{customdata}}<br>%{{x}}: %{{y:.{q.digits}f}} {q.unit}"
    data: list[dict[str, object]] = [
        # a line through the points (markers for thousands of points would slow the page)
        {"type": "scatter", "mode": "lines+markers" if len(pts) <= 60 else "lines",
         "name": "accepted run", "x": xs, "y": values,
         "customdata": [f"/runs/{p['run']}" for p in pts],
         "line": {"color": "#0969da", "width": 1}, "marker": {"size": 5},
         "hovertemplate": hover + "<extra></extra>"},
        {"type": "scatter", "mode": "markers", "name": "out of control",
         "x": [p["t"] for p, _ in bad], "y": [v for _, v in bad],
         "customdata": [f"/runs/{p['run']}" for p, _ in bad],
         "text": [", ".join(f"rule {r}" for r in p["rules"]) for p, _ in bad],
         "marker": {"size": 8, "color": FLAG, "symbol": "x"},
         "hovertemplate": hover + "<br>%{text}<extra></extra>"},
    ]
    lo = min(min(values), lim["lower"] * k)
    hi = max(max(values), lim["upper"] * k)
    pad = 0.15 * (hi - lo) or 0.5 * 10.0 ** -q.digits
    window = (lo - pad, hi + pad)
    lines: list[tuple[float, str | None, str, str]] = [
        (lim["centre"] * k, "centre line", "#1a7f37", "solid"),
        (lim["upper"] * k, "±3σ control limits", FLAG, "dash"),
        (lim["lower"] * k, None, FLAG, "dash")]
    off_scale = ""
    if lim["limit"] is not None:
        name = "drift limit (centre ± the recipe's drift)" if c["kind"] == "calibration" \
            else "the recipe's QA limit"
        if c["kind"] == "calibration" or c["param"] == "twist_deg":
            centre = lim["centre"] if c["kind"] == "calibration" else 0.0
            limits = [(centre + lim["limit"]) * k, (centre - lim["limit"]) * k]
        else:
            limits = [lim["limit"] * k]
        shown = [y for y in limits if window[0] <= y <= window[1]]
        for i, y in enumerate(shown):
            lines.append((y, name if i == 0 else None, "#9a6700", "dot"))
        if len(shown) < len(limits):
            spread = "±" if len(limits) == 2 else "≤ "
            off_scale = (f"; the recipe's limit ({spread}"
                         f"{display.number(c['param'], lim['limit'])}) is off the scale")
    for y, line_name, colour, dash in lines:
        data.append({"type": "scatter", "mode": "lines", "x": [xs[0], xs[-1]], "y": [y, y],
                     "name": line_name or "", "showlegend": line_name is not None,
                     "hoverinfo": "skip",
                     "line": {"color": colour, "dash": dash, "width": 1.5}})
    title = (f"{c['label']} on {c['station']}: {c['flagged']} of {len(pts)} out of control"
             f"{off_scale}")
    return {"data": data, "layout": _layout(
        title, c["short"], height=300, xaxis={"type": "date", "automargin": True},
        yaxis={"title": {"text": c["short"]}, "automargin": True, "range": list(window),
               "tickformat": f".{q.digits}f"})}


def comparison_figure(rows: list[ComparisonRow]) -> Figure:
    """Parameters on every station side by side, one panel each, in the unit shown:
    quartiles, whiskers (click a station's box: its runs). One figure, so the page draws it
    at once; each panel's name sits above it, where it cannot run into its neighbour's."""
    data: list[dict[str, object]] = []
    n = max(1, len(rows))
    annotations: list[dict[str, object]] = []
    layout = _layout("station against station", "", height=320,
                     grid={"rows": 1, "columns": n, "pattern": "independent", "xgap": 0.35},
                     showlegend=False, annotations=annotations,
                     margin={"l": 50, "r": 20, "t": 70, "b": 60})
    for i, row in enumerate(rows, start=1):
        st = row["stations"]
        k = display.quantity(row["param"]).factor
        suffix = "" if i == 1 else str(i)
        data.append({
            "type": "box", "name": row["label"], "x": [s["station"] for s in st],
            "q1": [s["q1"] * k for s in st], "median": [s["median"] * k for s in st],
            "q3": [s["q3"] * k for s in st], "lowerfence": [s["low"] * k for s in st],
            "upperfence": [s["high"] * k for s in st],
            "customdata": [history_link(station=s["station"]) for s in st],
            "xaxis": f"x{suffix}", "yaxis": f"y{suffix}", "marker": {"color": "#0969da"}})
        layout[f"xaxis{suffix}"] = {"type": "category", "automargin": True,
                                    "tickfont": {"size": 10}}
        layout[f"yaxis{suffix}"] = {"automargin": True, "tickfont": {"size": 10}}
        annotations.append({
            "text": row["short"], "showarrow": False, "font": {"size": 12},
            "xref": f"x{suffix} domain", "yref": "paper", "x": 0.5, "y": 1.02,
            "xanchor": "center", "yanchor": "bottom"})
    return {"data": data, "layout": layout}


def figures(data: DashboardData) -> dict[str, Figure]:
    """Every figure of the dashboard by the id of its element."""
    out = {"yield": yield_figure(data), "cycle": cycle_figure(data),
           "pareto": pareto_figure(data)}
    for c in data["charts"]:
        out[f"chart-{c['param']}"] = control_figure(c)
    shown = [row for row in data["comparison"] if row["param"] in data["params"]]
    if shown:
        out["compare"] = comparison_figure(shown)
    return out
