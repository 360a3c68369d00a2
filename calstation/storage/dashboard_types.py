"""The QA dashboard's data (:func:`calstation.storage.dashboard.dashboard`) as typed mappings:
what its page, its JSON twin and its figures (:mod:`.dashboard_figures`) read. Stored units."""

from __future__ import annotations

import datetime as dt
from typing import TypedDict

Figure = dict[str, object]
"""A plotly figure (``data`` and ``layout``), only ever written out as JSON."""


class DashboardRun(TypedDict):
    """One run of the period (:func:`calstation.storage.dashboard._runs`)."""

    id: int
    station: str
    started: dt.datetime | None
    status: str
    cycle_s: float | None
    first_pass: bool


YieldRow = TypedDict("YieldRow", {
    "station": str, "period": str, "since": str | None, "until": str | None, "runs": int,
    "finished": int, "passed": int, "first_pass": int, "yield": float | None,
    "first_pass_yield": float | None, "median_cycle_s": float | None})
"""Runs, yield, first-pass yield and median cycle time of a station in a period (``all``: the
whole window)."""


class ParetoRow(TypedDict):
    """Failed or aborted runs of one step and reason, with the cumulative share (0–1)."""

    reason: str
    step: str
    limit: str
    status: str
    count: int
    cumulative: float


class Series(TypedDict):
    """One parameter of one station: ``run``, ``t`` (text for people) and ``value`` (stored
    units), oldest first, as parallel lists, and ``limit``: the newest run's recipe limit."""

    run: list[int]
    t: list[str]
    value: list[float]
    limit: float | None


class ChartLimits(TypedDict):
    """A control chart's centre line, σ, ±3σ, baseline and the recipe's limit."""

    centre: float
    sigma: float
    upper: float
    lower: float
    baseline: int
    limit: float | None


class ChartPoint(TypedDict):
    """A point of a control chart with the Western Electric rules it breaks."""

    run: int
    t: str
    value: float
    rules: list[int]


class Chart(TypedDict):
    """A control chart of one parameter on one station (:func:`.dashboard.chart`)."""

    station: str
    param: str
    label: str
    short: str
    unit: str
    kind: str
    points: list[ChartPoint]
    limits: ChartLimits | None
    flagged: int


class StationSpread(TypedDict):
    """One station's spread of a parameter: quartiles, whiskers, points out of control."""

    station: str
    n: int
    q1: float
    median: float
    q3: float
    low: float
    high: float
    centre: float
    sigma: float
    flagged: int


class ComparisonRow(TypedDict):
    """A parameter on every station side by side."""

    param: str
    label: str
    short: str
    unit: str
    stations: list[StationSpread]


class Period(TypedDict):
    """The dashboard's window: first and last day, days, grouping."""

    since: str
    until: str
    days: int
    group: str


class DashboardData(TypedDict):
    """Everything the dashboard page draws (:func:`.dashboard.dashboard`)."""

    period: Period
    stations: list[str]
    station: str | None
    params: list[str]
    labels: dict[str, str]
    units: dict[str, str]
    rules: dict[int, str]
    yields: list[YieldRow]
    pareto: list[ParetoRow]
    charts: list[Chart]
    comparison: list[ComparisonRow]
