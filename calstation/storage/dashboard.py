"""The QA dashboard's data: yields, the failure Pareto, cycle times and control charts of every
station over a period, from the stored runs (the statistics themselves: :mod:`.spc`).

Plain data in stored units (metres, radians, the cube's angles in degrees, seconds), each chart
and row saying its ``unit``; times as UTC text for people; the JSON twin of ``/dashboard``.
:mod:`.dashboard_figures` turns it into plotly figures, in the units shown
(:mod:`calstation.display`). The queries read
columns, not ORM objects, so a fleet's eight weeks (9,000 runs) load in a fraction of a second.
"""

from __future__ import annotations

import datetime as dt
import gc
import math
import re
from collections import defaultdict
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Literal

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from calstation import display
from calstation.errors import CalstationError
from calstation.storage.dashboard_types import (
    Chart,
    ComparisonRow,
    DashboardData,
    DashboardRun,
    ParetoRow,
    Series,
    StationSpread,
    YieldRow,
)
from calstation.storage.db import (
    Calibration,
    CubeCheckRecord,
    Database,
    Run,
    RunStatus,
    Station,
    Step,
    StepStatus,
)
from calstation.storage.spc import (
    RULES,
    Yield,
    control_limits,
    out_of_control,
    pareto,
    western_electric,
)

CALIBRATION_PARAMS = ("tx", "ty", "tz", "ry", "rz")
"""The calibration's parameters a chart is offered for (rx is the gauge, held at 0)."""
CUBE_PARAMS = ("edge_error", "obb_error", "flatness_rms", "perpendicularity_deg", "twist_deg")
"""The cube check's measures a chart is offered for."""
CHART_PARAMS = CALIBRATION_PARAMS + CUBE_PARAMS

LABELS: dict[str, str] = {p: display.quantity(p).title for p in ("rx", *CHART_PARAMS)}
"""What each parameter is called on the QA pages, with its display unit."""

SHORT: dict[str, str] = {p: display.quantity(p).heading for p in ("rx", *CHART_PARAMS)}
"""The same, short enough for a chart's axis."""

UNITS: dict[str, str] = display.units(CHART_PARAMS)
"""The unit each charted value is given in (the stored one: m, rad, deg)."""

REASONS: tuple[tuple[str, str], ...] = (
    ("lines were lost", "lidar lines lost"),
    ("face-fit edge error", "cube edge error (face fit)"),
    ("OBB edge error", "cube edge error (oriented box)"),
    ("face flatness", "cube face flatness"),
    ("perpendicularity", "cube perpendicularity"),
    ("side faces twisted", "cube twist (ry)"),
    ("twist of the side faces", "cube twist not measurable"),
    ("too few returns for a plane fit", "cube faces not seen"),
    ("max_sigma.", "σ above calibration.max_sigma"),
    ("drift", "drift between calibrations"),
)
"""(text in a step's error, the limit it names): how a failure is filed in the Pareto."""

DEFAULT_DAYS = 56
MAX_DAYS = 366


ENDED_BADLY = (RunStatus.FAILED, RunStatus.ABORTED)
"""The statuses of the runs the failure Pareto counts."""


class DashboardError(CalstationError):
    """A dashboard filter that cannot be used (HTTP 400)."""


@dataclass
class DashboardQuery:
    """What the dashboard shows: the period (``days`` up to ``until``, a date; default today),
    grouped by ``day`` or ``week``, and the charts of ``params`` for ``station`` (default: the
    first station)."""

    station: str | None = None
    days: int = DEFAULT_DAYS
    group: Literal["day", "week"] = "week"
    params: list[str] = field(default_factory=lambda: ["tx", "ty", "tz", "ry", "rz"])
    until: str | None = None

    def window(self) -> tuple[dt.datetime, dt.datetime]:
        """The period as [start, end) in UTC."""
        if not 1 <= self.days <= MAX_DAYS:
            raise DashboardError(f"days: {self.days} is not between 1 and {MAX_DAYS}")
        for p in self.params:
            if p not in CHART_PARAMS:
                raise DashboardError(f"param: {p!r} is not one of {', '.join(CHART_PARAMS)}")
        try:
            day = (dt.date.fromisoformat(self.until.strip()) if self.until
                   else dt.datetime.now(dt.UTC).date())
        except ValueError as exc:
            raise DashboardError(f"until: {self.until!r} is not a date (YYYY-MM-DD)") from exc
        end = dt.datetime.combine(day + dt.timedelta(days=1), dt.time(), tzinfo=dt.UTC)
        return end - dt.timedelta(days=self.days), end


def utc(t: dt.datetime | None) -> dt.datetime | None:
    """A stored time as aware UTC (SQLite returns naive UTC)."""
    if t is None:
        return None
    return t.replace(tzinfo=dt.UTC) if t.tzinfo is None else t.astimezone(dt.UTC)


def when(t: dt.datetime | None) -> str:
    """A time for people: ``2026-11-23 14:05`` (UTC, to the minute)."""
    u = utc(t)
    return "—" if u is None else u.isoformat(sep=" ", timespec="minutes")[:16]


def period_of(t: dt.datetime, group: str) -> tuple[str, dt.date, dt.date]:
    """The day or ISO week ``t`` falls in: its label and its first and last day."""
    day = t.date()
    if group == "day":
        return day.isoformat(), day, day
    year, week, _ = day.isocalendar()
    monday = day - dt.timedelta(days=day.weekday())
    return f"{year}-W{week:02d}", monday, monday + dt.timedelta(days=6)


def failure_reason(step: str | None, error: str | None) -> tuple[str, str]:
    """(failed step, limit) of a failure, from the step's error text."""
    text = error or ""
    for needle, limit in REASONS:
        if needle in text:
            return step or "run", limit
    first = re.split(r"[:;(.]", text.strip(), maxsplit=1)[0].strip()
    return step or "run", (first[:60] or "no message")


def reason_text(reason: str) -> str:
    """The words of a step's error behind a limit as :func:`failure_reason` names it (the
    history's ``reason`` filter); other text is taken as it is."""
    return next((needle for needle, limit in REASONS if limit == reason), reason)


@contextmanager
def _without_gc_pauses() -> Iterator[None]:
    """The cyclic garbage collector off while the dashboard builds its ~100,000 small objects
    (none in a cycle): its passes over them took a third of the time. Reference counting still
    frees everything; the collector is back on after."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def dashboard(db: Database, q: DashboardQuery) -> DashboardData:
    """Everything the dashboard page draws (see the module's docstring). The database is read
    in one short read-only session; the statistics are computed after it."""
    with _without_gc_pauses():
        return _dashboard(db, q)


def _dashboard(db: Database, q: DashboardQuery) -> DashboardData:
    start, end = q.window()
    with db.session("reading the runs for the dashboard", read_only=True) as session:
        stations = list(session.scalars(select(Station.name).order_by(Station.name)))
        station = q.station or (stations[0] if stations else None)
        if station is not None and station not in stations:
            raise DashboardError(f"station: {station!r} has no run (stations: "
                                 f"{', '.join(stations) or 'none'})")
        runs = _runs(session, start, end)
        pareto_rows = _pareto(session, runs, start, end)
        series = _series(session, start, end)
    return {
        "period": {"since": start.date().isoformat(),
                   "until": (end - dt.timedelta(days=1)).date().isoformat(),
                   "days": q.days, "group": q.group},
        "stations": stations, "station": station, "params": list(q.params),
        "labels": LABELS, "units": UNITS, "rules": RULES,
        "yields": _yields(runs, q.group),
        "pareto": pareto_rows,
        "charts": [chart(series.get((station, p)), station, p)
                   for p in q.params] if station else [],
        "comparison": _comparison(series, stations),
    }


def _runs(session: Session, start: dt.datetime, end: dt.datetime) -> list[DashboardRun]:
    """The period's runs: station, times, status, serial, whether a step was repeated, and
    whether an earlier run had the same serial."""
    retried = set(session.scalars(select(Step.run_id).where(Step.attempt > 1)))
    first_of_serial = dict(session.execute(
        select(Run.unit_serial, func.min(Run.id)).where(Run.unit_serial.is_not(None))
        .group_by(Run.unit_serial)).all())
    rows = session.execute(
        select(Run.id, Station.name, Run.started_at, Run.finished_at, Run.status,
               Run.unit_serial).join(Station, Run.station_id == Station.id)
        .where(Run.started_at >= start, Run.started_at < end).order_by(Run.started_at)).all()
    out: list[DashboardRun] = []
    for run_id, station, started, finished, status, serial in rows:
        s, f = utc(started), utc(finished)
        out.append({
            "id": run_id, "station": station, "started": s, "status": status,
            "cycle_s": (f - s).total_seconds() if s and f else None,
            "first_pass": run_id not in retried
            and (serial is None or first_of_serial.get(serial) == run_id),
        })
    return out


def _yields(runs: list[DashboardRun], group: str) -> list[YieldRow]:
    """Per station and period: runs, yield, first-pass yield, median cycle time; and the
    station's whole period (``period`` "all")."""
    groups: dict[tuple[str, str], Yield] = defaultdict(Yield)
    spans: dict[str, tuple[dt.date | None, dt.date | None]] = {}
    for r in runs:
        started = r["started"]
        assert started is not None  # a run's start is never empty
        label, first, last = period_of(started, group)
        spans[label] = (first, last)
        for key in ((r["station"], label), (r["station"], "all")):
            groups[key].add(r["status"], r["first_pass"], r["cycle_s"])
    out: list[YieldRow] = []
    for (station, label), y in sorted(groups.items()):
        since, until = spans.get(label, (None, None))
        out.append({"station": station, "period": label,
                    "since": since.isoformat() if since else None,
                    "until": until.isoformat() if until else None,
                    "runs": y.runs, "finished": y.finished, "passed": y.passed,
                    "first_pass": y.first_pass, "yield": y.yield_,
                    "first_pass_yield": y.first_pass_yield,
                    "median_cycle_s": y.median_cycle_s})
    return out


def _pareto(session: Session, runs: list[DashboardRun], start: dt.datetime,
            end: dt.datetime) -> list[ParetoRow]:
    """Failed runs by (failed step, limit), most frequent first; aborted runs by the step
    they stopped in."""
    ended = {r["id"]: r for r in runs if r["status"] in ENDED_BADLY}
    last_failed: dict[int, tuple[str | None, str | None]] = {}
    for run_id, failed_step, failed_error in session.execute(
            select(Step.run_id, Step.name, Step.error).join(Run, Step.run_id == Run.id)
            .where(Run.started_at >= start, Run.started_at < end,
                   Run.status.in_(ENDED_BADLY),
                   Step.status.in_((StepStatus.FAILED, StepStatus.ABORTED)))
            .order_by(Step.run_id, Step.id)).all():
        last_failed[run_id] = (failed_step, failed_error)
    reasons: list[str] = []
    keys: dict[str, tuple[str, str, str]] = {}
    for run_id, r in ended.items():
        step_name, error = last_failed.get(run_id, (None, None))
        step, limit = (failure_reason(step_name, error) if r["status"] == RunStatus.FAILED
                       else (step_name or "run", "aborted"))
        key = f"{step}: {limit}"
        reasons.append(key)
        keys[key] = (step, limit, r["status"])
    return [{"reason": key, "step": keys[key][0], "limit": keys[key][1],
             "status": keys[key][2], "count": n, "cumulative": share}
            for key, n, share in pareto(reasons)]


def _series(session: Session, start: dt.datetime, end: dt.datetime
            ) -> dict[tuple[str, str], Series]:
    """Every charted value of the period by (station, parameter)."""
    limits = _recipe_limits(session, start, end)
    out: dict[tuple[str, str], Series] = {}

    def add(params: tuple[str, ...], rows: Iterable[Sequence[object]]) -> None:
        for row in rows:  # (run id, station, started, recipe sha256, *values)
            run_id, station, started, sha = row[0], str(row[1]), row[2], str(row[3])
            assert isinstance(run_id, int) and isinstance(started, dt.datetime | None)
            t = when(started)
            lim = limits.get(sha, {})
            for p, v in zip(params, row[4:], strict=True):
                if v is None:
                    continue
                assert isinstance(v, float | int)
                series = out.get((station, p))
                if series is None:
                    series = out[(station, p)] = {"run": [], "t": [], "value": [],
                                                  "limit": None}
                series["run"].append(run_id)
                series["t"].append(t)
                series["value"].append(float(v))
                series["limit"] = lim.get(p, series["limit"])

    head = (Run.id, Station.name, Run.started_at, Run.recipe_sha256)
    window = (Run.started_at >= start, Run.started_at < end)
    add(CALIBRATION_PARAMS, session.execute(
        select(*head, *(getattr(Calibration, p) for p in CALIBRATION_PARAMS))
        .join(Station, Run.station_id == Station.id)
        .join(Calibration, Calibration.run_id == Run.id)
        .where(Calibration.accepted, *window).order_by(Run.started_at, Run.id)))
    newest = (select(func.max(CubeCheckRecord.id)).group_by(CubeCheckRecord.run_id)
              .scalar_subquery())
    add(CUBE_PARAMS, session.execute(
        select(*head, *(getattr(CubeCheckRecord, p) for p in CUBE_PARAMS))
        .join(Station, Run.station_id == Station.id)
        .join(CubeCheckRecord, CubeCheckRecord.run_id == Run.id)
        .where(CubeCheckRecord.id.in_(newest), *window).order_by(Run.started_at, Run.id)))
    return out


def _recipe_limits(session: Session, start: dt.datetime, end: dt.datetime
                   ) -> dict[str, dict[str, float]]:
    """Each recipe's limits by its sha256 (stored units): the drift limit of a calibration
    parameter, the QA limit of a cube measure. A recipe that no longer parses has none."""
    from calstation.recipes import parse_recipe

    out: dict[str, dict[str, float]] = {}
    for sha, text in session.execute(
            select(Run.recipe_sha256, func.min(Run.recipe_text))
            .where(Run.started_at >= start, Run.started_at < end)
            .group_by(Run.recipe_sha256)).all():
        try:
            qa = parse_recipe(text, "recipe stored with the run").qa
        except CalstationError:
            continue
        t, r = qa.drift_translation, math.radians(qa.drift_rotation_deg)
        out[sha] = {"tx": t, "ty": t, "tz": t, "ry": r, "rz": r,
                    "edge_error": qa.edge_error, "obb_error": qa.obb_edge_error,
                    "flatness_rms": qa.flatness_rms,
                    "perpendicularity_deg": qa.perpendicularity_deg, "twist_deg": qa.twist_deg}
    return out


def chart(series: Series | None, station: str, param: str) -> Chart:
    """A control chart of ``param`` on ``station``: centre line, ±3σ, the recipe's limit, and
    each point with the Western Electric rules it breaks."""
    base: Chart = {"station": station, "param": param, "label": LABELS[param],
                            "short": SHORT[param], "unit": UNITS[param],
                            "kind": "calibration" if param in CALIBRATION_PARAMS else "cube",
                            "points": [], "limits": None, "flagged": 0}
    if not series or not series["value"]:
        return base
    lim = control_limits(series["value"])
    flags = western_electric(series["value"], lim)
    base["limits"] = {"centre": lim.centre, "sigma": lim.sigma, "upper": lim.upper,
                      "lower": lim.lower, "baseline": lim.baseline, "limit": series["limit"]}
    base["points"] = [{"run": r, "t": t, "value": v, "rules": f} for r, t, v, f in
                      zip(series["run"], series["t"], series["value"], flags, strict=True)]
    base["flagged"] = sum(1 for f in flags if f)
    return base


def _comparison(series: dict[tuple[str, str], Series], stations: list[str]
                ) -> list[ComparisonRow]:
    """Station against station: for every parameter, each station's spread (quartiles, the
    whiskers at 1.5 IQR) and its points out of control."""
    import numpy as np

    out: list[ComparisonRow] = []
    for p in CHART_PARAMS:
        rows: list[StationSpread] = []
        for s in stations:
            one = series.get((s, p))
            if not one or not one["value"]:
                continue
            v = np.array(one["value"])
            q1, med, q3 = (float(x) for x in np.percentile(v, [25, 50, 75]))
            iqr = q3 - q1
            lim = control_limits(one["value"])
            rows.append({"station": s, "n": int(v.size), "q1": q1, "median": med, "q3": q3,
                         "low": float(v[v >= q1 - 1.5 * iqr].min()),
                         "high": float(v[v <= q3 + 1.5 * iqr].max()),
                         "centre": lim.centre, "sigma": lim.sigma,
                         "flagged": out_of_control(one["value"], lim)})
        if rows:
            out.append({"param": p, "label": LABELS[p], "short": SHORT[p], "unit": UNITS[p],
                        "stations": rows})
    return out
