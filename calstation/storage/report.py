"""Run records as plain mappings, and the exports of a run's calibration.

What ``calstation show --json`` prints, what the ``calstation_run_finished`` hook receives and what
the station writes to ``report.json`` are one mapping, built here from the database rows; values
are exactly what is stored (metres, radians, UTC ISO-8601 times).
"""

from __future__ import annotations

import csv
import datetime as dt
import io
import json
from typing import TYPE_CHECKING, TypedDict

from sqlalchemy import Select, select
from sqlalchemy.orm import Session, selectinload

from calstation import display
from calstation.errors import DatabaseError
from calstation.jsonvalue import JSONObject
from calstation.plugins.hookspecs import ArtifactRecord, RunBrief, StepRecord
from calstation.storage.db import PARAMS, Calibration, CubeCheckRecord, Run
from calstation.storage.db.models import MAX_ROW_ID

if TYPE_CHECKING:
    from calstation.storage.ros import Frames

EXPORT_FORMATS = ("yaml", "json", "urdf", "xacro", "csv", "tf", "ros2-yaml", "ros2-params")

CUBE_UNITS: dict[str, str] = {
    "obb_edges": "m", "obb_error": "m", "face_edges": "m", "edge_error": "m",
    "flatness_rms": "m", "flatness_excess": "m", "range_noise": "m",
    "perpendicularity_deg": "deg", "twist_deg": "deg", "twist_sigma_deg": "deg"}
"""The unit of each value of a stored cube check (:func:`cube_dict`)."""


class CalibrationRecord(TypedDict):
    """A stored calibration (:func:`calibration_dict`)."""

    id: int
    stage: str
    strategy: str
    accepted: bool
    refused: list[str]
    H: dict[str, float]
    sigma: dict[str, float | None]
    units: dict[str, str]
    not_estimated: list[str]
    encoder_latency_s: float | None
    sigma_encoder_latency_s: float | None
    range_offset: float | None
    sigma_range_offset: float | None
    range_scale: float | None
    sigma_range_scale: float | None
    incidence_bias: float | None
    sigma_incidence_bias: float | None
    predicted_error_m: float | None
    budget_m: float | None
    cost: float | None
    iterations: int | None
    diagnostics: JSONObject | None
    created_at: str | None


class CubeRecord(TypedDict):
    """A stored cube check (:func:`cube_dict`)."""

    id: int
    calibration_id: int | None
    obb_edges: list[float]
    obb_error: float | None
    face_edges: list[float]
    edge_error: float | None
    height_judged: bool
    flatness_rms: float | None
    flatness_excess: float | None
    range_noise: float | None
    perpendicularity_deg: float | None
    twist_deg: float | None
    twist_sigma_deg: float | None
    units: dict[str, str]
    passed: bool
    failures: list[str]
    created_at: str | None


class HistoryItem(RunBrief):
    """A run as the history lists it (:func:`history_item`)."""

    calibration: CalibrationRecord | None
    cube_check: CubeRecord | None


class RunSummary(RunBrief):
    """Everything stored about a run (:func:`run_summary`): the observer hooks' summary
    (:class:`calstation.plugins.hookspecs.RunSummary`) with its calibrations and cube check
    typed."""

    steps: list[StepRecord]
    calibrations: list[CalibrationRecord]
    cube_check: CubeRecord | None
    qa_limits: JSONObject | None
    artifacts: list[ArtifactRecord]


def iso(t: dt.datetime | None) -> str | None:
    """UTC ISO-8601 text of a stored time (SQLite returns naive UTC)."""
    if t is None:
        return None
    if t.tzinfo is None:
        t = t.replace(tzinfo=dt.UTC)
    return t.astimezone(dt.UTC).isoformat()


def json_float(value: object) -> float:
    """A number read from stored JSON as a float: ``float()`` of it, a TypeError for a value
    that is not a number or text."""
    if isinstance(value, str | int | float):
        return float(value)
    raise TypeError(f"not a number: {value!r}")


def run_brief(run: Run) -> RunBrief:
    """The run's own fields (no steps or results)."""
    return {
        "id": run.id,
        "station": run.station.name,
        "recipe_name": run.recipe_name,
        "recipe_path": run.recipe_path,
        "recipe_sha256": run.recipe_sha256,
        "operator": run.operator,
        "unit_serial": run.unit_serial,
        "unattended": run.unattended,
        "status": run.status,
        "started_at": iso(run.started_at),
        "finished_at": iso(run.finished_at),
        "data_dir": run.data_dir,
        "error": run.error,
        "host": run.host,
        "pid": run.pid,
        "motor_stop": run.motor_stop,
    }


def refused_reasons(c: Calibration) -> list[str]:
    """Why a re-processing result was refused (its σ over the recipe's
    ``calibration.max_sigma``, …): stored, never accepted; empty when it was not refused."""
    reprocess = (c.diagnostics or {}).get("reprocess")
    if not isinstance(reprocess, dict):
        return []
    return [str(r) for r in reprocess.get("refused") or []]


def calibration_dict(c: Calibration) -> CalibrationRecord:
    """A stored calibration: H and sigma (m, rad: ``units`` says which), the parameters held
    rather than estimated (``not_estimated``), the estimated encoder latency and its sigma
    (s, None when not estimated), the lidar's range model (``range_offset``, ``range_scale``,
    ``incidence_bias`` and their ``sigma_*``; m, dimensionless, m at 60°; None when not
    estimated), the predicted reconstruction error and the budget it was
    judged against (m, None when not predicted), cost, strategy, accepted, ``refused`` (the
    reasons a re-processing result was refused, else empty), diagnostics."""
    H, sigma = c.params(), c.sigmas()
    return {
        "id": c.id,
        "stage": c.stage,
        "strategy": c.strategy,
        "accepted": c.accepted,
        "refused": refused_reasons(c),
        "H": H,
        "sigma": sigma,
        "units": display.units(PARAMS),
        "not_estimated": [p for p in PARAMS if display.not_estimated(H[p], sigma[p])],
        "encoder_latency_s": c.encoder_latency_s,
        "sigma_encoder_latency_s": c.sigma_encoder_latency_s,
        "range_offset": c.range_offset,
        "sigma_range_offset": c.sigma_range_offset,
        "range_scale": c.range_scale,
        "sigma_range_scale": c.sigma_range_scale,
        "incidence_bias": c.incidence_bias,
        "sigma_incidence_bias": c.sigma_incidence_bias,
        "predicted_error_m": c.predicted_error_m,
        "budget_m": ((c.diagnostics or {}).get("predicted_error") or {}).get("budget_m"),
        "cost": c.cost,
        "iterations": c.iterations,
        "diagnostics": c.diagnostics,
        "created_at": iso(c.created_at),
    }


def with_results(stmt: Select[Run], *, steps: bool = False) -> Select[Run]:
    """``stmt``, a query of runs, loading their calibrations and cube checks (and their steps,
    with ``steps``) in one query each for all the runs, instead of one per run."""
    stmt = stmt.options(selectinload(Run.calibrations), selectinload(Run.cube_checks))
    return stmt.options(selectinload(Run.steps)) if steps else stmt


def history_item(run: Run) -> HistoryItem:
    """A run as the history lists it: :func:`run_brief`, its final calibration (the accepted
    one, else the last fine-tuning, else the last) and its last cube check."""
    fine = [c for c in run.calibrations if c.stage == "fine"]
    picks = [c for c in run.calibrations if c.accepted] or fine or run.calibrations
    return {
        **run_brief(run),
        "calibration": calibration_dict(picks[-1]) if picks else None,
        "cube_check": cube_dict(run.cube_checks[-1]) if run.cube_checks else None,
    }


def cube_dict(c: CubeCheckRecord) -> CubeRecord:
    """A stored cube check (lengths in metres, angles in degrees: ``units`` says which)."""
    return {
        "id": c.id,
        "calibration_id": c.calibration_id,
        "obb_edges": c.obb_edges,
        "obb_error": c.obb_error,
        "face_edges": c.face_edges,
        "edge_error": c.edge_error,
        "height_judged": bool(c.height_judged),
        "flatness_rms": c.flatness_rms,
        "flatness_excess": c.flatness_excess,
        "range_noise": c.range_noise,
        "perpendicularity_deg": c.perpendicularity_deg,
        "twist_deg": c.twist_deg,
        "twist_sigma_deg": c.twist_sigma_deg,
        "units": CUBE_UNITS,
        "passed": c.passed,
        "failures": c.failures,
        "created_at": iso(c.created_at),
    }


def run_summary(run: Run) -> RunSummary:
    """Everything stored about a run: brief, steps, calibrations, cube check, artifacts."""
    steps = {s.id: s.name for s in run.steps}
    return {
        **run_brief(run),
        "steps": [
            {
                "name": s.name,
                "attempt": s.attempt,
                "status": s.status,
                "started_at": iso(s.started_at),
                "finished_at": iso(s.finished_at),
                "result": s.result,
                "error": s.error,
            }
            for s in run.steps
        ],
        "calibrations": [calibration_dict(c) for c in run.calibrations],
        "cube_check": cube_dict(run.cube_checks[-1]) if run.cube_checks else None,
        "qa_limits": qa_limits(run.recipe_text),
        "artifacts": [
            {
                "kind": a.kind,
                "step": steps.get(a.step_id) if a.step_id is not None else None,
                "path": a.path,
                "size_bytes": a.size_bytes,
                "sha256": a.sha256,
                "status": a.status,
            }
            for a in run.artifacts
        ],
    }


def qa_limits(recipe_text: str) -> JSONObject | None:
    """The pass/fail and drift limits of a stored recipe (metres, degrees; ``qa`` section with its
    defaults), None when the text is not a recipe mapping."""
    import yaml
    from pydantic import ValidationError

    from calstation.recipes import QALimits

    try:
        data = yaml.safe_load(recipe_text)
        section = data.get("qa") if isinstance(data, dict) else None
        return QALimits.model_validate(section or {}).model_dump()
    except (yaml.YAMLError, ValidationError):
        return None


def find_run(session: Session, run_id: int) -> Run | None:
    """The run ``run_id``, None when there is none (an id no row can have, below 1 or past
    :data:`~calstation.storage.db.models.MAX_ROW_ID`, included: the database is not asked)."""
    if not 1 <= run_id <= MAX_ROW_ID:
        return None
    return session.get(Run, run_id)


def get_run(session: Session, run_id: int) -> Run:
    """The run ``run_id``; :class:`DatabaseError` if there is none."""
    run = find_run(session, run_id)
    if run is None:
        raise DatabaseError(f"no run with id {run_id} in the database")
    return run


def final_calibration(run: Run) -> Calibration:
    """The run's calibration to export: the accepted one, else the newest fine-tuned, else the
    initial; :class:`DatabaseError` if the run has none."""
    cals = run.calibrations
    for pick in (
        [c for c in cals if c.accepted],
        [c for c in cals if c.stage == "fine"],
        list(cals),
    ):
        if pick:
            return pick[-1]
    raise DatabaseError(f"run {run.id} has no calibration yet (status {run.status})")


def export_calibration(
    run: Run,
    fmt: str,
    *,
    parent: str = "lidar",
    frames: Frames | None = None,
    fragment: bool = False,
) -> str:
    """The run's final calibration as ``yaml``, ``json`` (both loadable by
    ``CalibrationResult.load``), ``csv`` (one header row and one value row, floats written
    exactly, booleans ``true``/``false``), or for ROS (:mod:`calstation.storage.ros`): ``tf``
    (``static_transform_publisher`` arguments, both directions), ``urdf`` (a complete
    ``<robot>`` file with the two links and the joint; with ``fragment``, the elements to paste
    into your own), ``xacro`` (a macro adding the joint between two links you name) or
    ``ros2-yaml`` (a ``geometry_msgs/TransformStamped``), ``ros2-params`` (a ROS 2 parameter
    file with the transform, the lidar's range model and the time offset). ``parent``
    (``lidar`` or ``platform``) picks the direction of the URDF joint and the
    TransformStamped; ``frames`` the frame ids. The lidar's range model (DESIGN §9), when
    estimated, is in every format: fields of yaml, json, csv and ros2-params, and a comment
    (with how to correct a range) in the others."""
    from calstation.engine.frames import Extrinsics
    from calstation.storage import ros

    if fmt not in EXPORT_FORMATS:
        raise DatabaseError(
            f"unknown export format {fmt!r}; use one of {', '.join(EXPORT_FORMATS)}"
        )
    if fragment and fmt != "urdf":
        raise DatabaseError(f"a fragment is a URDF form: give --format urdf, not {fmt}")
    cal = final_calibration(run)
    H = Extrinsics.from_dict(cal.params())
    names = frames or ros.Frames()
    title = (
        f"calstation run {run.id}, station {run.station.name}: {cal.stage} calibration "
        f"({cal.strategy}{', accepted' if cal.accepted else ''})"
    )
    if cal.encoder_latency_s is not None:
        sigma_ms = "" if cal.sigma_encoder_latency_s is None else (
            f" ± {cal.sigma_encoder_latency_s * 1e3:.3f}")
        title += (f"; lidar–encoder time offset {cal.encoder_latency_s * 1e3:.3f}{sigma_ms} ms "
                  "(encoder time minus lidar time)")
    if cal.range_offset is not None:
        title += f"; {ros.range_note(cal.range_fields())}"
    if fmt == "ros2-params":
        return ros.ros2_params_export(H, title, names, parent, cal.range_fields(),
                                      cal.encoder_latency_s)
    if fmt == "tf":
        return ros.tf_export(H, title, names)
    if fmt in ("urdf", "xacro"):
        form = "xacro" if fmt == "xacro" else "fragment" if fragment else "robot"
        return ros.urdf_export(H, title, names, parent, form)
    if fmt == "ros2-yaml":
        created = cal.created_at
        stamp = round(
            (created if created.tzinfo else created.replace(tzinfo=dt.UTC)).timestamp() * 1e9
        )
        return ros.ros2_yaml_export(H, title, stamp, names, parent)
    if fmt == "csv":
        buf = io.StringIO()
        header = ["run_id", "station", "stage", "strategy", "accepted", *PARAMS]
        header += [f"sigma_{p}" for p in PARAMS] + ["cost", "iterations"]
        header += ["encoder_latency_s", "sigma_encoder_latency_s"]
        header += list(cal.range_fields())
        header += ["qx", "qy", "qz", "qw"]  # rotation of P in L, quaternion order x y z w
        row: list[object] = [run.id, run.station.name, cal.stage, cal.strategy,
                          "true" if cal.accepted else "false"]
        row += [repr(v) for v in cal.params().values()]
        row += ["" if s is None else repr(s) for s in cal.sigmas().values()]
        row += ["" if cal.cost is None else repr(cal.cost), cal.iterations]
        row += ["" if v is None else repr(v)
                for v in (cal.encoder_latency_s, cal.sigma_encoder_latency_s)]
        row += ["" if v is None else repr(v) for v in cal.range_fields().values()]
        row += [repr(float(q)) for q in H.as_quaternion()]
        writer = csv.writer(buf, lineterminator="\n")
        writer.writerow(header)
        writer.writerow(row)
        return buf.getvalue()
    data = cal.result().to_dict()
    data["run"] = {
        "id": run.id,
        "station": run.station.name,
        "stage": cal.stage,
        "accepted": cal.accepted,
        "recipe_name": run.recipe_name,
        "recipe_sha256": run.recipe_sha256,
        "status": run.status,
    }
    if fmt == "json":
        return json.dumps(data, indent=2) + "\n"
    import yaml

    return yaml.safe_dump(data, sort_keys=False)


def previous_accepted(session: Session, run: Run) -> Calibration | None:
    """The station's accepted calibration from the newest passed run before ``run``."""
    stmt = (
        select(Calibration)
        .join(Run, Calibration.run_id == Run.id)
        .where(Run.station_id == run.station_id, Run.id < run.id, Calibration.accepted)
        .order_by(Run.id.desc())
        .limit(1)
    )
    return session.scalars(stmt).first()
