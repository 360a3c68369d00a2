"""The records of the run report (:mod:`calstation.storage.report_html`): what it shows, as
typed mappings; the web run page's JSON twin and the end screen read them."""

from __future__ import annotations

from typing import NotRequired, TypedDict

import numpy as np
from numpy.typing import NDArray

from calstation.jsonvalue import JSONObject, JSONValue
from calstation.plugins.hookspecs import ArtifactRecord, RunBrief, StepRecord
from calstation.storage.report import CalibrationRecord, CubeRecord

Figure = dict[str, object]
"""A plotly figure (``data`` and ``layout``), only ever written out as JSON."""


class Residuals(TypedDict):
    """A 3D view's residual statistics (metres); ``values`` every finite residual."""

    median: float | None
    p95: float | None
    unit: str
    values: NDArray[np.float64]


class View(TypedDict):
    """One 3D view of the report: its figure and residuals, or why there is none."""

    title: str
    error: NotRequired[str]
    points: NotRequired[int]
    shown: NotRequired[int]
    figure: NotRequired[Figure]
    residual_kind: NotRequired[str]
    residual: NotRequired[Residuals]
    note: NotRequired[str]


class Accuracy(TypedDict):
    """The predicted reconstruction error beside its budget (:func:`accuracy_of`)."""

    error_m: float
    budget_m: float | None
    holds: bool | None
    level: JSONValue
    radius_m: float | None
    height_m: float | None
    turns: JSONValue
    bias_m: float
    text: str


class CubeRow(TypedDict):
    """A measured cube value beside its limit (:func:`cube_rows`)."""

    name: str
    quantity: str
    value: float | None
    limit: float | None
    unit: str
    ok: bool | None


class CalibrationRow(TypedDict):
    """A stored calibration as the report lists it (:func:`calibration_rows`)."""

    id: int
    stage: str
    strategy: str
    accepted: bool
    cost: float | None
    iterations: int | None
    values: dict[str, float]
    sigma: dict[str, float | None]
    units: dict[str, str]
    not_estimated: list[str]
    gauge: JSONValue
    time_offset_s: float | None
    time_offset_sigma_s: float | None
    range_model: str | None
    timings: JSONValue


class StepRow(StepRecord):
    """A step attempt with its title and duration (s) (:func:`step_rows`)."""

    title: str
    duration_s: float | None


class ReportRun(RunBrief):
    """The run's own fields and its recipe's QA limits."""

    qa_limits: JSONObject | None


class ReportData(TypedDict):
    """Everything the report shows (:func:`report_data`; the web run page's JSON twin)."""

    run: ReportRun
    serial: str | None
    verdict: str
    final: CalibrationRecord | None
    calibrations: list[CalibrationRow]
    cube: CubeRecord | None
    cube_rows: list[CubeRow]
    steps: list[StepRow]
    artifacts: list[ArtifactRecord]
    drift: JSONObject | None
    qa: JSONObject | None
    views: list[View]
    figures: dict[str, Figure]
    accuracy: Accuracy | None
    generated_at: str
    partial: NotRequired[str | None]
    range_residuals: NotRequired[str]
    """what the cube's range residuals say (:func:`range_residuals_text`), when it has them"""


class ViewsData(TypedDict):
    """The 3D views as the web run page fetches them (:func:`views_data`)."""

    views: list[dict[str, object]]
    residuals: Figure | None
    key: list[object]


class SerialStep(TypedDict):
    """What :func:`unit_serial` reads of a step attempt."""

    name: str
    status: str
    result: JSONObject | None
