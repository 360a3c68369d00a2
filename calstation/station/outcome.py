"""What a step hands back to the station: :class:`StepOutcome` (its result, files and the rows to
store with it), made JSON-ready by :func:`plain`; and :func:`format_h`, how an H reads on the
console."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, TypedDict, overload

import numpy as np

from calstation import display
from calstation.jsonvalue import JSONObject, JSONValue
from calstation.storage.db import RunStatus

if TYPE_CHECKING:
    from calstation.engine.result import CalibrationResult


class CubeMeasurements(TypedDict):
    """A cube check as a run stores it (the ``cube_check`` row, the cube scan's result):
    lengths in metres, angles in degrees, None for a value that is not a number."""

    obb_edges: list[float | None]
    obb_error: float | None
    obb_excess: float | None
    face_edges: list[float | None]
    edge_error: float | None
    height_judged: bool
    flatness_rms: float | None
    flatness_excess: float | None
    range_noise: float | None
    perpendicularity_deg: float | None
    perpendicularity_sigma_deg: float | None
    twist_deg: float | None
    twist_sigma_deg: float | None
    passed: bool
    failures: list[str]


@dataclass
class StepOutcome:
    """What a step produced: its JSON result, files, and database results to store with it."""

    result: JSONObject
    artifacts: list[tuple[str, Path]] = field(default_factory=list)
    calibration: tuple[str, CalibrationResult] | None = None
    cube: tuple[int | None, CubeMeasurements] | None = None
    """(calibration id, check); None as the id: the calibration this step stores"""
    failure: str | None = None
    """A failed QA verdict: the step fails (the operator may retry) but keeps what it stored."""
    staged: list[tuple[str, Path, Path]] = field(default_factory=list)
    """(kind, temporary file, final path): moved into place once the step is stored."""
    run_status: RunStatus | None = None
    """The run's verdict, stored with the step (the report step)."""
    accept_calibration: int | None = None
    """The calibration the verdict accepts (the report step of a passed run)."""
    drift_failure: str | None = None
    """Why the run fails although its cube check passed (the report step: the calibration
    drifted and ``qa.drift_fails`` is set); the station ends the run with it as its reason."""


@overload
def plain(value: Mapping[str, object]) -> JSONObject: ...


@overload
def plain(value: list[object] | tuple[object, ...] | np.ndarray) -> list[JSONValue]: ...


@overload
def plain(value: float | np.floating) -> float | None: ...


@overload
def plain(value: object) -> JSONValue: ...


def plain(value: object) -> JSONValue:
    """JSON-ready copy: numpy → Python, NaN/inf → None, tuples → lists, keys → str (and any
    other object, which JSON could not hold, its text)."""
    if isinstance(value, Mapping):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [plain(v) for v in value]
    if isinstance(value, np.ndarray):
        items: list[object] = value.tolist()
        return plain(items)
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, float | np.floating):
        f = float(value)
        return f if math.isfinite(f) else None
    if isinstance(value, Path):
        return str(value)
    if value is None or isinstance(value, str | int):
        return value
    return str(value)


def format_h(H: Mapping[str, float], sigma: Mapping[str, float] | None = None) -> str:
    """An H for the operator: translations in mm, rotations in degrees
    (:mod:`calstation.display`); with ``sigma``, a parameter held rather than estimated reads
    ``not estimated``."""
    return ", ".join(
        f"{k} {display.NOT_ESTIMATED}" if sigma is not None
        and display.not_estimated(v, sigma.get(k)) else f"{k} {display.number(k, v)}"
        for k, v in H.items())
