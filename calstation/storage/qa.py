"""The QA engineer's queries behind the web pages: history, trends, two runs side by side.

Plain data (stored units: metres, radians, UTC ISO-8601), the JSON twins of the pages; the
templates convert to millimetres and degrees.
"""

from __future__ import annotations

import datetime as dt
import itertools
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, TypedDict

from sqlalchemy import Select, and_, func, select
from sqlalchemy.orm import Session

from calstation import display
from calstation.errors import CalstationError
from calstation.recipes import parse_recipe
from calstation.storage.db import PARAMS, Calibration, Run, RunStatus, Station, Step, StepStatus
from calstation.storage.report import HistoryItem, history_item, iso, json_float, with_results

if TYPE_CHECKING:
    from calstation.recipes import QALimits
    from calstation.storage.report_types import ReportData

STATUSES = (RunStatus.RUNNING, RunStatus.PASSED, RunStatus.FAILED, RunStatus.ABORTED)
STEP_NAMES = ("preflight", "place", "static_scan", "spin_scan", "fine_tune", "cube_scan",
              "report")
"""The steps a run may fail in (the history's ``failed_step`` filter offers them)."""
TREND_PARAMS = tuple(p for p in PARAMS if p != "rx")  # rx is the gauge, held at 0
CUBE_TREND_PARAMS = ("edge_error", "obb_error", "flatness_rms", "perpendicularity_deg",
                     "twist_deg")


class TrendPoint(TypedDict):
    """One accepted calibration of a trend (:func:`trend_points`; stored units)."""

    run_id: int
    date: str | None
    unit_serial: str | None
    value: float
    sigma: float | None
    delta: float | None
    limit: float
    flagged: bool


class Trend(TypedDict):
    """One parameter of a station over time (:func:`trend`)."""

    station: str
    param: str
    unit: str
    limit_kind: str
    points: list[TrendPoint]


class CompareRow(TypedDict):
    """One value of two runs side by side (:func:`compare`; stored units)."""

    name: str
    quantity: str | None
    unit: str | None
    a: float | None
    b: float | None
    sigma_a: float | None
    sigma_b: float | None
    not_estimated_a: bool
    not_estimated_b: bool
    diff: float | None
    limit: float | None
    flagged: bool


class QueryError(CalstationError):
    """A filter the QA pages cannot use (HTTP 400)."""


@dataclass
class HistoryFilter:
    """Filters of the history page (all optional)."""

    station: str | None = None
    status: str | None = None
    operator: str | None = None
    serial: str | None = None
    """Part of the unit's serial (any case)."""
    since: str | None = None
    until: str | None = None
    failed_step: str | None = None
    reason: str | None = None
    limit: int = 200

    def as_dict(self) -> dict[str, str | int]:
        """The filters as given (for the page and its JSON twin)."""
        return {k: v for k, v in vars(self).items() if v not in (None, "")}


def parse_date(text: str, field: str, end: bool = False) -> dt.datetime:
    """A date (``2026-11-23``, whole day) or ISO time, UTC."""
    try:
        value = dt.datetime.fromisoformat(text.strip())
        if value.tzinfo is None:
            value = value.replace(tzinfo=dt.UTC)
        if end and len(text.strip()) == 10:
            value += dt.timedelta(days=1)
    except (ValueError, OverflowError) as exc:  # 9999-12-31 has no next day
        raise QueryError(f"{field}: {text!r} is not a date (YYYY-MM-DD) or ISO time") from exc
    return value


class HistoryRow(HistoryItem):
    """A run as the web's history lists it: with its unit's serial."""

    serial: str | None


def history(session: Session, f: HistoryFilter) -> list[HistoryRow]:
    """Runs, newest first, each with its final calibration and cube check."""
    from calstation.storage.report_html import unit_serial

    if f.status and f.status not in STATUSES:
        raise QueryError(f"status: {f.status!r} is not one of {', '.join(STATUSES)}")
    stmt = with_results(select(Run).join(Station).order_by(Run.id.desc()), steps=True)
    if f.station:
        stmt = stmt.where(Station.name == f.station)
    if f.status:
        stmt = stmt.where(Run.status == f.status)
    if f.operator:
        stmt = stmt.where(Run.operator == f.operator)
    if f.since:
        stmt = stmt.where(Run.started_at >= parse_date(f.since, "since"))
    if f.until:
        stmt = stmt.where(Run.started_at < parse_date(f.until, "until", end=True))
    if f.serial:
        stmt = stmt.where(func.lower(Run.unit_serial).contains(f.serial.lower(),
                                                               autoescape=True))
    stmt = _failure_filters(stmt, f)
    rows: list[HistoryRow] = []
    for run in session.scalars(stmt.limit(max(1, min(f.limit, 5000)) * (4 if f.serial else 1))):
        item = history_item(run)
        serial = unit_serial(item["unit_serial"], item["data_dir"], [
            {"name": s.name, "status": s.status, "result": s.result} for s in run.steps])
        if f.serial and f.serial.lower() not in (serial or "").lower():
            continue
        rows.append({**item, "serial": serial})
        if len(rows) >= f.limit:
            break
    return rows


def _failure_filters(stmt: Select[Run], f: HistoryFilter) -> Select[Run]:
    """Runs with a step that failed (or was aborted) as ``f.failed_step``, and whose error
    names ``f.reason`` (a limit as the dashboard's Pareto names it, or words of the error)."""
    from calstation.storage.dashboard import reason_text

    conditions = []
    if f.failed_step:
        conditions.append(Step.name == f.failed_step)
    if f.reason:
        conditions.append(Step.error.contains(reason_text(f.reason), autoescape=True))
    if conditions:
        ended = Step.status.in_((StepStatus.FAILED, StepStatus.ABORTED))
        stmt = stmt.where(Run.steps.any(and_(ended, *conditions)))
    return stmt


def choices(session: Session) -> dict[str, list[str]]:
    """Values offered by the history filters: stations and operators seen."""
    return {
        "stations": list(session.scalars(select(Station.name).order_by(Station.name))),
        "operators": list(session.scalars(select(Run.operator).distinct().order_by(Run.operator))),
        "statuses": list(STATUSES),
        "steps": list(STEP_NAMES),
    }


def trend(
    session: Session, station: str, param: str, serial: str | None = None
) -> Trend:
    """One parameter of ``station``'s accepted calibrations (of unit ``serial`` only, when
    given) by date, with 1σ and drift limits: :func:`trend_points` (in ``unit``, the stored
    one) and how to draw them.
    :class:`QueryError` for a parameter the trend page does not offer."""
    if param not in TREND_PARAMS + CUBE_TREND_PARAMS:
        raise QueryError(
            f"param: {param!r} is not one of {', '.join(TREND_PARAMS + CUBE_TREND_PARAMS)}")
    kind = "cube" if param in CUBE_TREND_PARAMS else "drift"
    return {"station": station, "param": param, "unit": display.quantity(param).stored,
            "limit_kind": kind, "points": trend_points(session, station, param, serial)}


def trend_points(
    session: Session, station: str, param: str, serial: str | None = None
) -> list[TrendPoint]:
    """``param`` (a calibration parameter, or a cube figure of :data:`CUBE_TREND_PARAMS`) of
    ``station``'s accepted calibrations, of unit ``serial`` only when given, by the run's
    start date.

    Each point: run_id, date (UTC ISO-8601), unit_serial, value and sigma (m/rad; sigma None
    when not estimated), delta to the previous point, limit (the run's recipe's drift limit,
    or the cube limit), flagged.
    """
    stmt = (
        select(Run, Calibration)
        .join(Station, Run.station_id == Station.id)
        .join(Calibration, Calibration.run_id == Run.id)
        .where(Station.name == station, Calibration.accepted)
        .order_by(Run.started_at, Run.id)
    )
    if serial:
        stmt = stmt.where(Run.unit_serial == serial)
    points: list[TrendPoint] = []
    previous: float | None = None
    recipes: dict[str, QALimits] = {}
    for run, cal in session.execute(stmt).all():
        qa = recipes.get(run.recipe_sha256)
        if qa is None:
            qa = recipes[run.recipe_sha256] = parse_recipe(
                run.recipe_text, f"recipe of run {run.id}").qa
        sigma: float | None = None
        if param in CUBE_TREND_PARAMS:
            if not run.cube_checks or getattr(run.cube_checks[-1], param) is None:
                continue
            value = float(getattr(run.cube_checks[-1], param))
            limit = {"edge_error": qa.edge_error, "obb_error": qa.obb_edge_error,
                     "flatness_rms": qa.flatness_rms, "perpendicularity_deg":
                     qa.perpendicularity_deg, "twist_deg": qa.twist_deg}[param]
            flagged = abs(value) > limit
            delta = None if previous is None else value - previous
        else:
            value = float(getattr(cal, param))
            sigma = getattr(cal, f"sigma_{param}")
            limit = (qa.drift_translation if param.startswith("t")
                     else math.radians(qa.drift_rotation_deg))
            delta = None if previous is None else value - previous
            flagged = delta is not None and abs(delta) > limit
        points.append({"run_id": run.id, "date": iso(run.started_at),
                       "unit_serial": run.unit_serial, "value": value, "sigma": sigma,
                       "delta": delta, "limit": limit, "flagged": flagged})
        previous = value
    return points


def trend_figure(t: Trend) -> dict[str, object]:
    """A plotly figure of a trend: values with 1σ bars by date, the limits drawn."""
    from calstation.storage.dashboard import LABELS, SHORT

    k = display.quantity(t["param"]).factor
    label = LABELS.get(t["param"], t["param"])
    pts = t["points"]
    dates = [(p["date"] or "")[:19].replace("T", " ") for p in pts]  # UTC, to the second
    values = [p["value"] * k for p in pts]
    data: list[dict[str, object]] = [{
        "type": "scatter", "mode": "lines+markers", "name": label, "x": dates, "y": values,
        "text": [f"run {p['run_id']}" for p in pts],
        "customdata": [f"/runs/{p['run_id']}" for p in pts],
        "error_y": {"type": "data", "visible": True,
                    "array": [0.0 if p["sigma"] is None else p["sigma"] * k for p in pts]},
        "marker": {"size": 8, "color": ["#cf222e" if p["flagged"] else "#0969da" for p in pts]},
    }]
    if t["limit_kind"] == "drift" and len(pts) > 1:
        # the allowed band of each run: the previous value ± the drift limit
        for sign, name in ((1.0, "drift limit"), (-1.0, None)):
            xs: list[str | None] = []
            ys: list[float | None] = []
            for (a, b), (da, db) in zip(itertools.pairwise(pts), itertools.pairwise(dates),
                                        strict=True):
                level = (a["value"] + sign * b["limit"]) * k
                xs += [da, db, None]
                ys += [level, level, None]
            data.append({"type": "scatter", "mode": "lines", "name": name or "", "x": xs,
                         "y": ys, "showlegend": name is not None, "hoverinfo": "skip",
                         "line": {"dash": "dot", "color": "#1a7f37"}})
    elif t["limit_kind"] == "cube" and pts:
        signs = (1.0, -1.0) if t["param"] == "twist_deg" else (1.0,)
        for sign in signs:
            data.append({"type": "scatter", "mode": "lines", "name": "limit", "x": dates,
                         "y": [sign * p["limit"] * k for p in pts], "showlegend": sign > 0,
                         "line": {"dash": "dash", "color": "#cf222e"}, "hoverinfo": "skip"})
    return {"data": data, "layout": {
        "height": 340, "margin": {"l": 80, "r": 20, "t": 40, "b": 60},
        "title": {"text": f"{label} on station {t['station']}", "x": 0.01},
        "xaxis": {"title": {"text": "date (UTC)"}, "automargin": True, "type": "date"},
        "yaxis": {"title": {"text": SHORT.get(t["param"], label)}, "automargin": True},
        "legend": {"orientation": "h", "y": -0.3}, "hovermode": "closest",
    }}


def compare(a: ReportData, b: ReportData) -> list[CompareRow]:
    """Rows of two runs' final calibrations and cube checks side by side, in stored units
    (``unit``; ``quantity`` names how each is shown). A parameter one of the runs did not
    estimate has no difference and is never flagged; a difference within 3σ of the two runs
    is not flagged either (it is not a measured change)."""
    rows: list[CompareRow] = []
    fa, fb = a["final"], b["final"]
    qa_b = b["qa"] or {}
    drift_t, drift_r = qa_b.get("drift_translation"), qa_b.get("drift_rotation_deg")
    for p in PARAMS:
        va, vb = (fa["H"][p] if fa else None), (fb["H"][p] if fb else None)
        sa, sb = (fa["sigma"][p] if fa else None), (fb["sigma"][p] if fb else None)
        held_a = fa is not None and display.not_estimated(va, sa)
        held_b = fb is not None and display.not_estimated(vb, sb)
        # the drift limit of B's recipe: how far a station may move between calibrations
        limit = ((None if drift_t is None else json_float(drift_t)) if p.startswith("t")
                 else None if drift_r is None
                 else math.radians(json_float(drift_r)))
        diff = None if va is None or vb is None or held_a or held_b else vb - va
        noise = 3.0 * math.hypot(sa or 0.0, sb or 0.0)
        rows.append({"name": p, "quantity": p, "unit": display.quantity(p).stored,
                     "a": va, "b": vb, "sigma_a": sa, "sigma_b": sb,
                     "not_estimated_a": held_a, "not_estimated_b": held_b,
                     "diff": diff, "limit": limit,
                     "flagged": diff is not None and limit is not None
                     and abs(diff) > max(limit, noise)})
    ra = {r["name"]: r for r in a["cube_rows"]}
    rb = {r["name"]: r for r in b["cube_rows"]}
    for name in list(ra) or list(rb):
        x, y = ra.get(name), rb.get(name)
        va, vb = (x["value"] if x else None), (y["value"] if y else None)
        q = (x["quantity"] if x else None) or (y["quantity"] if y else None)
        rows.append({"name": name, "quantity": q,
                     "unit": (x["unit"] if x else None) or (y["unit"] if y else None),
                     "a": va, "b": vb, "sigma_a": None, "sigma_b": None,
                     "not_estimated_a": False, "not_estimated_b": False,
                     "diff": None if va is None or vb is None else vb - va,
                     "limit": y["limit"] if y else x["limit"] if x else None,
                     "flagged": y is not None and y["ok"] is False})
    return rows
