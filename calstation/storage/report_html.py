"""The run report: ``runs/N/report.html``, one self-contained file that opens offline.

Fed only by what the station already stores: the run's database rows (:func:`report.run_summary`),
the recipe text stored with the run (its QA limits and fixture geometry) and the recordings in the
run folder (reconstructed with the run's final calibration for the 3D views). plotly.js comes from
the installed ``plotly`` package and is inlined, so the file needs no network; the web station
renders the same template with plotly served from its own ``/static``.

What it holds: the verdict, H with its 1σ (mm, degrees), every measured value of the cube check
beside its limit, interactive subsampled 3D views of the reconstructed spin target (coloured by
half-turn; its residual is the distance to the nearest point of the other half-turn) and cube
(coloured by residual: the distance to the plane through its nearest points), the residual
histogram, the cost per iteration when the strategy reports it, the
steps with their timings and the recordings with their sha256. A print stylesheet keeps it
readable on paper (the 3D views print as the browser draws them; every number is in a table).
"""

from __future__ import annotations

import base64
import datetime as dt
import json
import math
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calstation import display
from calstation.atomic import write_atomic
from calstation.errors import CalstationError
from calstation.jsonvalue import JSONObject, JSONValue
from calstation.plugins.hookspecs import ArtifactRecord, StepRecord
from calstation.storage.db import Database, Run, RunStatus, StepStatus
from calstation.storage.report import (
    CalibrationRecord,
    CubeRecord,
    RunSummary,
    json_float,
)
from calstation.storage.report_residuals import (
    range_residuals_figure,
    range_residuals_of,
    range_residuals_text,
)
from calstation.storage.report_types import (
    Accuracy,
    CalibrationRow,
    CubeRow,
    Figure,
    ReportData,
    Residuals,
    SerialStep,
    StepRow,
    View,
    ViewsData,
)
from calstation.storage.templating import (
    plotly_js as plotly_js,
    plotly_style_ids as plotly_style_ids,
)

MAX_CLOUD_POINTS = 12_000
"""Points per 3D view (a subsample: the report stays a few MB)."""

MAX_RESIDUAL_POINTS = 20_000
"""Points of each half-turn used for the residual (nearest neighbour) statistics."""

SEED = 0
"""The subsample is drawn with this seed: the same run gives the same report."""

PARAMS = display.H_PARAMS
"""The calibration's parameters in the order the report lists them."""

if TYPE_CHECKING:
    from calstation.engine.frames import Extrinsics
    from calstation.recipes import QALimits, Recipe


@dataclass
class Cloud:
    """A subsampled reconstructed cloud for one 3D view: (N, 3) mm in frame D, one value each."""

    title: str
    points_mm: NDArray[np.float64]
    values: NDArray[np.float64]
    color_label: str
    categorical: bool


def _rng() -> np.random.Generator:
    return np.random.default_rng(SEED)


def _subsample(n: int, k: int, rng: np.random.Generator) -> NDArray[np.int64]:
    if n <= k:
        return np.arange(n)
    return np.sort(rng.choice(n, size=k, replace=False))


def reconstructed_object(
    path: Path, H: Extrinsics, platter_radius: float
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """The object on the platter from a spin recording: (N, 3) points in D (metres) above the
    platter top and inside its radius, and (N,) True for the first half-turn (φ mod 2π < π)."""
    from calstation.engine.reconstruct import lidar_points_to_dynamic
    from calstation.recordings.reader import read_recording

    recording = read_recording(path)
    p_L, phi = recording.points_lidar()
    p_D = lidar_points_to_dynamic(p_L, phi, H)
    radial = np.hypot(p_D[:, 1], p_D[:, 2])
    keep = (p_D[:, 0] > 0.002) & (p_D[:, 0] < 0.5) & (radial < platter_radius)
    first = np.mod(phi[keep], 2.0 * np.pi) < np.pi
    return p_D[keep], first


def half_turn_residuals(
    points: NDArray[np.float64], first: NDArray[np.bool_]
) -> NDArray[np.float64]:
    """Distance (m) from each point to the nearest point of the other half-turn.

    Both half-turns see the same surfaces when H is right (DESIGN §5), so these distances are
    what the periodicity cost drives down; with a wrong H they grow. ``inf`` when one half-turn is
    empty.
    """
    from scipy.spatial import cKDTree

    out = np.full(points.shape[0], np.inf)
    a, b = points[first], points[~first]
    if a.shape[0] == 0 or b.shape[0] == 0:
        return out
    out[first] = cKDTree(b).query(a, k=1)[0]
    out[~first] = cKDTree(a).query(b, k=1)[0]
    return out


def local_plane_residuals(points: NDArray[np.float64], k: int = 20) -> NDArray[np.float64]:
    """Distance (m) of each point to the plane fitted (PCA) to its ``k`` nearest neighbours.

    Small on a flat, well reconstructed face (the range noise); large at mixed pixels and where
    a wrong H smears a face. Used for the cube, whose vertical faces each half-turn sees from
    a different side (so a half-turn distance would mean nothing there).
    """
    from scipy.spatial import cKDTree

    n = points.shape[0]
    if n <= k:
        return np.full(n, np.inf)
    _, idx = cKDTree(points).query(points, k=k)
    nb = points[idx]  # (N, k, 3)
    centred = nb - nb.mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", centred, centred) / k
    _, vecs = np.linalg.eigh(cov)
    normal = vecs[:, :, 0]  # the smallest eigenvalue's vector
    out: NDArray[np.float64] = np.abs(
        np.einsum("ni,ni->n", points - nb.mean(axis=1), normal))
    return out


def _cloud(path: Path, H: Extrinsics, platter_radius: float, title: str, by: str) -> View:
    """One 3D view and its residual statistics, as plain data for the template.

    ``by``: ``"half-turn"`` (colour by half-turn; residual = distance to the other half-turn)
    or ``"plane"`` (colour by the distance to the local plane, which is also the residual).
    """
    rng = _rng()
    points, first = reconstructed_object(path, H, platter_radius)
    if points.shape[0] < 30:
        return {"title": title, "error": f"only {points.shape[0]} points above the platter"}
    pick = _subsample(points.shape[0], MAX_RESIDUAL_POINTS * 2, rng)
    pts, fst = points[pick], first[pick]
    residual = half_turn_residuals(pts, fst) if by == "half-turn" else local_plane_residuals(pts)
    show = _subsample(pts.shape[0], MAX_CLOUD_POINTS, rng)
    finite = residual[np.isfinite(residual)]
    cloud = Cloud(
        title=title,
        points_mm=pts[show] * 1000.0,
        values=(fst[show].astype(np.float64) if by == "half-turn" else residual[show] * 1000.0),
        color_label="half-turn" if by == "half-turn" else "residual (mm)",
        categorical=by == "half-turn",
    )
    residuals: Residuals = {
        "median": float(np.median(finite)) if finite.size else None,
        "p95": float(np.percentile(finite, 95)) if finite.size else None,
        "unit": "m",
        "values": np.clip(finite, 0, None),
    }
    kind = ("distance to the nearest point of the other half-turn" if by == "half-turn"
            else "distance to the plane through the 20 nearest points")
    return {
        "title": title,
        "points": int(points.shape[0]),
        "shown": int(show.shape[0]),
        "figure": _cloud_figure(cloud),
        "residual_kind": kind,
        "residual": residuals,
        "note": residual_note(int(show.shape[0]), int(points.shape[0]), kind, residuals, by),
    }


def residual_note(shown: int, points: int, kind: str, residual: Residuals, by: str) -> str:
    """What a 3D view's residuals are, and what is normal for them: they measure the range
    noise and the spacing of the points as much as the calibration, whose own share is the
    predicted reconstruction error."""
    normal = ("Two half-turns of a well calibrated station see the same surfaces through the "
              "range noise and between scan lines, so a median of a millimetre or two is "
              "normal; a wrong H shows as a median well above the range noise and a doubled "
              "outline." if by == "half-turn" else
              "On a flat face this is the range noise; mixed pixels at the edges make the tail.")
    return (f"{shown} of {points} points above the platter; residual ({kind}): median "
            f"{display.number('residual', residual['median'])}, 95th percentile "
            f"{display.number('residual', residual['p95'])}. {normal} What the calibration "
            "itself adds is the predicted reconstruction error above.")


def typed(values: ArrayLike) -> dict[str, str]:
    """An array as plotly.js reads it in binary: float32, base64 (a quarter of the text of
    JSON numbers; plotly's own ``{dtype, bdata}`` typed-array form)."""
    data = np.ascontiguousarray(np.asarray(values, dtype="<f4"))
    return {"dtype": "f4", "bdata": base64.b64encode(data.tobytes()).decode("ascii")}


def _cloud_figure(c: Cloud) -> Figure:
    """A plotly ``scatter3d`` figure (plain JSON, the points in binary): x_D is up."""
    p = c.points_mm
    # plotly's z is up: show (y_D, z_D, x_D) so the platter lies flat
    xyz = {"x": typed(p[:, 1]), "y": typed(p[:, 2]), "z": typed(p[:, 0])}
    marker: dict[str, object] = {"size": 1.6}
    traces: list[dict[str, object]]
    if c.categorical:
        traces = []
        for value, name, colour in ((1.0, "first half-turn", "#1f77b4"),
                                    (0.0, "second half-turn", "#ff7f0e")):
            m = c.values == value
            traces.append({
                "type": "scatter3d", "mode": "markers", "name": name,
                "x": typed(p[m, 1]), "y": typed(p[m, 2]), "z": typed(p[m, 0]),
                "marker": {**marker, "color": colour},
            })
    else:
        v = np.where(np.isfinite(c.values), c.values, np.nan)
        # the scale follows the bulk of the surface, not the stray mixed pixels
        hi = 3.0 * float(np.nanmedian(v)) if np.isfinite(v).any() else 1.0
        # a point with no residual (nan) takes the top of the scale
        traces = [{
            "type": "scatter3d", "mode": "markers", "name": c.color_label, **xyz,
            "marker": {**marker, "color": typed(np.where(np.isfinite(v), v, hi)),
                       "colorscale": "Viridis", "cmin": 0.0, "cmax": max(hi, 1e-3),
                       "colorbar": {"title": {"text": c.color_label}}},
        }]
    layout = {
        "margin": {"l": 0, "r": 0, "t": 30, "b": 0},
        "title": {"text": c.title},
        "scene": {
            "aspectmode": "data",
            "xaxis": {"title": {"text": "y_D (mm)"}},
            "yaxis": {"title": {"text": "z_D (mm)"}},
            "zaxis": {"title": {"text": "x_D (mm, up)"}},
        },
        "legend": {"orientation": "h"},
        "height": 420,
    }
    return {"data": traces, "layout": layout}


def _histogram_figure(clouds: list[View]) -> Figure | None:
    traces: list[dict[str, object]] = [
        {"type": "histogram", "name": c["title"],
         "x": typed(display.quantity("residual").factor * c["residual"]["values"]),
         "opacity": 0.6, "xbins": {"start": 0.0, "size": 0.1}}
        for c in clouds if c.get("residual") and len(c["residual"]["values"])
    ]
    if not traces:
        return None
    return {
        "data": traces,
        "layout": {
            "barmode": "overlay", "height": 300, "margin": {"l": 50, "r": 10, "t": 30, "b": 40},
            "title": {"text": "residuals (see each view for what they measure)"},
            "xaxis": {"title": {"text": "mm"}, "range": [0, max(
                2.0, *(4.0 * (display.shown("residual", c["residual"]["median"]) or 0)
                       for c in clouds if c.get("residual")))]},
            "yaxis": {"title": {"text": "points"}},
        },
    }


def _certificate(calibration: CalibrationRecord) -> dict[str, JSONValue] | None:
    """The lidar's range offset certificate the calibration combined, as stored; None."""
    said = _diagnostic(calibration, "certificate")
    return said if isinstance(said, dict) else None


def _diagnostic(calibration: CalibrationRecord | None, key: str) -> JSONValue:
    """``key`` of the calibration's stored diagnostics; None when absent."""
    diagnostics = calibration["diagnostics"] if calibration is not None else None
    return (diagnostics or {}).get(key)


def _iterated(calibrations: list[CalibrationRecord], final: CalibrationRecord | None
              ) -> CalibrationRecord | None:
    """The calibration whose solver reported its iterations: the final one, else the newest
    that did (the fine-tuning under a combined ``periodicity+cube`` calibration)."""
    for c in ([final] if final else []) + list(reversed(calibrations)):
        if isinstance(_diagnostic(c, "iterations"), list):
            return c
    return None


def _cost_figure(calibration: CalibrationRecord | None) -> Figure | None:
    """Cost per outer iteration (periodicity's ``diagnostics.iterations``), when reported."""
    if calibration is None:
        return None
    history = _diagnostic(calibration, "iterations")
    if not isinstance(history, list) or not history:
        return None
    costs = [h.get("cost") for h in history if isinstance(h, dict)]
    if not costs or any(c is None for c in costs):
        return None
    rms = [math.sqrt(json_float(c)) * 1000.0 for c in costs if c is not None]
    labels = [
        f"stage {h.get('stage', '?')}, {h.get('matches', '?')} matches"
        for h in history if isinstance(h, dict)
    ]
    return {
        "data": [
            {"type": "scatter", "mode": "lines+markers", "name": "RMS residual (mm)",
             "x": list(range(1, len(rms) + 1)), "y": rms, "text": labels},
        ],
        "layout": {
            "height": 300, "margin": {"l": 50, "r": 20, "t": 30, "b": 40},
            "title": {"text": f"cost per iteration of the {calibration.get('stage', '')} "
                              f"calibration ({calibration.get('strategy', '')}): RMS residual; "
                              "stage and matches on hover"},
            "xaxis": {"title": {"text": "outer iteration"}, "dtick": 1},
            "yaxis": {"title": {"text": "RMS residual (mm)"}, "type": "log"},
        },
    }


def accuracy_of(calibration: CalibrationRecord | None) -> Accuracy | None:
    """The predicted reconstruction error of ``calibration`` beside its budget (metres), when it
    was predicted: error, budget, level, work volume, turns, the bias bound, whether it holds."""
    if calibration is None:
        return None
    record = _diagnostic(calibration, "predicted_error")
    if not isinstance(record, dict) or record.get("max_m") is None:
        return None
    volume = _mapping(record.get("work_volume"))
    budget = record.get("budget_m")
    return {
        "error_m": json_float(record["max_m"]),
        "budget_m": None if budget is None else json_float(budget),
        "holds": None if budget is None else json_float(record["max_m"]) <= json_float(budget),
        "level": record.get("level", 0.95),
        "radius_m": None if "radius_m" not in volume else json_float(volume["radius_m"]),
        "height_m": None if "height_m" not in volume else json_float(volume["height_m"]),
        "turns": record.get("turns"),
        "bias_m": json_float(record.get("bias_m") or 0.0),
        "text": accuracy_text(record),
    }


def _mapping(value: JSONValue) -> JSONObject:
    """``value`` when it is a mapping, else an empty one (absent, None)."""
    return value if isinstance(value, dict) else {}


def accuracy_text(record: JSONObject) -> str:
    """The predicted error beside its budget in words: ``0.089 mm at 95 % over r 292 mm ×
    h 150 mm, after 1 turn, within the budget of 0.300 mm``."""
    error, budget = record.get("max_m"), record.get("budget_m")
    volume = _mapping(record.get("work_volume"))
    text = (f"{display.number('predicted_error', error)} at "
            f"{display.percent(record.get('level', 0.95), 0)}")
    if volume:
        text += (f" over r {display.number('distance', volume.get('radius_m'))} × h "
                 f"{display.number('distance', volume.get('height_m'))}")
    turns = record.get("turns")
    if isinstance(turns, int | float):
        text += f", after {display.count(turns, 'turn')}"
    if budget is not None and error is not None:
        text += (f", {'within' if json_float(error) <= json_float(budget) else 'above'} the budget "
                 f"of {display.number('predicted_error', budget)}")
    return text


def _accuracy_figure(calibration: CalibrationRecord | None) -> Figure | None:
    """Where in the work volume the predicted error is largest: each point's error over the
    volume, seen from above (y_D, z_D) and from the side (distance from the axis, height)."""
    record = _mapping(_diagnostic(calibration, "predicted_error"))
    points = record.get("map")
    if not points:
        return None
    arr = np.asarray(points, dtype=np.float64)
    err = arr[:, 3] * 1e3
    radial = np.hypot(arr[:, 1], arr[:, 2]) * 1e3
    marker = {"color": err.round(4).tolist(), "colorscale": "Viridis", "size": 7,
              "cmin": 0.0, "cmax": float(err.max()) if err.size else 1.0,
              "colorbar": {"title": {"text": "mm"}}}
    top = arr[:, 0] >= arr[:, 0].max() - 1e-9
    return {
        "data": [
            {"type": "scatter", "mode": "markers", "name": "top of the volume, from above",
             "x": (arr[top, 1] * 1e3).round(1).tolist(), "y": (arr[top, 2] * 1e3).round(1).tolist(),
             "marker": {**marker, "color": err[top].round(4).tolist()}, "xaxis": "x",
             "yaxis": "y", "text": [f"{e:.3f} mm" for e in err[top]]},
            {"type": "scatter", "mode": "markers", "name": "every height, from the side",
             "x": radial.round(1).tolist(), "y": (arr[:, 0] * 1e3).round(1).tolist(),
             "marker": {**marker, "showscale": False}, "xaxis": "x2", "yaxis": "y2",
             "text": [f"{e:.3f} mm" for e in err]},
        ],
        "layout": {
            "height": 340, "margin": {"l": 50, "r": 20, "t": 40, "b": 40}, "showlegend": False,
            "title": {"text": "predicted error over the work volume (mm at the budget's level)"},
            "grid": {"rows": 1, "columns": 2, "pattern": "independent"},
            "xaxis": {"title": {"text": "y_D (mm), top of the volume"}},
            "yaxis": {"title": {"text": "z_D (mm)"}, "scaleanchor": "x"},
            "xaxis2": {"title": {"text": "distance from the axis (mm)"}},
            "yaxis2": {"title": {"text": "height above the platter (mm)"}},
        },
    }


# --- gathering -------------------------------------------------------------------------------
def _limits(recipe_text: str) -> Recipe | None:
    from calstation.recipes import parse_recipe

    try:
        return parse_recipe(recipe_text, "recipe stored with the run")
    except CalstationError:
        return None


def _flatness_rows(cube: CubeRecord, qa: QALimits | None
                   ) -> list[tuple[str, str, float | None, float | None]]:
    """The faces' flatness: the RMS beyond the range noise against the limit, with the raw RMS
    beside it (a check stored before the excess was measured judged the raw RMS)."""
    limit = getattr(qa, "flatness_rms", None)
    if cube.get("flatness_excess") is None:
        return [("face flatness (RMS)", "flatness_rms", cube.get("flatness_rms"), limit)]
    return [("face flatness beyond the range noise (RMS)", "flatness_excess",
             cube.get("flatness_excess"), limit),
            ("face flatness (RMS, range noise included)", "flatness_rms",
             cube.get("flatness_rms"), None)]


def cube_rows(cube: CubeRecord | None, qa: QALimits | None) -> list[CubeRow]:
    """Each measured cube value beside its limit and whether it passes: ``name`` (in words),
    ``quantity`` (:mod:`calstation.display`), ``value`` and ``limit`` in ``unit``, the stored
    unit (None: a value shown for information, judged by no limit)."""
    if cube is None:
        return []
    rows: list[tuple[str, str, float | None, float | None]] = [
        ("face-fit edge error", "edge_error", cube.get("edge_error"),
         getattr(qa, "edge_error", None)),
        ("OBB edge error (paper metric)", "obb_error", cube.get("obb_error"),
         getattr(qa, "obb_edge_error", None)),
        *_flatness_rows(cube, qa),
        ("perpendicularity", "perpendicularity_deg", cube.get("perpendicularity_deg"),
         getattr(qa, "perpendicularity_deg", None)),
    ]
    twist = cube.get("twist_deg")
    if twist is not None:  # checks stored before the twist measure have none
        # the ry correction that makes the side faces flattest: its size against the limit
        # it fails beyond the limit and beyond 3σ: the larger of the two is its limit
        limit = getattr(qa, "twist_deg", None)
        sigma = cube.get("twist_sigma_deg")
        if limit is not None and sigma is not None and math.isfinite(float(sigma)):
            limit = max(float(limit), 3.0 * float(sigma))
        rows.append(("side-face twist |δ| (ry check)", "twist_deg", abs(float(twist)), limit))
    out: list[CubeRow] = []
    for name, q, value, limit in rows:
        v = None if value is None else float(value)
        lim = None if limit is None else float(limit)
        ok = None if v is None or lim is None or not math.isfinite(v) else v <= lim
        out.append({"name": name, "quantity": q, "value": v, "limit": lim,
                    "unit": display.quantity(q).stored, "ok": ok})
    return out


def calibration_rows(calibrations: list[CalibrationRecord]) -> list[CalibrationRow]:
    """Every stored calibration: H and 1σ as stored (``units`` says which), the parameters
    held rather than estimated, the lidar–encoder time offset and its σ (s) where a second
    pass estimated it, and the lidar's range model in words where it was estimated
    (:func:`calstation.engine.rangemodel.describe`)."""
    from calstation.engine.rangemodel import describe

    rows: list[CalibrationRow] = []
    for c in calibrations:
        rows.append({
            "id": c["id"], "stage": c["stage"], "strategy": c["strategy"],
            "accepted": c["accepted"], "cost": c["cost"], "iterations": c["iterations"],
            "values": dict(c["H"]), "sigma": dict(c["sigma"]),
            "units": display.units(c["H"]),
            "not_estimated": [p for p in c["H"]
                              if display.not_estimated(c["H"][p], c["sigma"].get(p))],
            "gauge": _diagnostic(c, "gauge_note"),
            "time_offset_s": c["encoder_latency_s"],
            "time_offset_sigma_s": c["sigma_encoder_latency_s"],
            "range_model": describe(range_fields(c), _certificate(c)),
            "timings": _diagnostic(c, "timings") or {},
        })
    return rows


def range_fields(c: CalibrationRecord) -> dict[str, float | None]:
    """The lidar's range model of a stored calibration (DESIGN §9; None where not estimated)."""
    return {"range_offset": c["range_offset"], "sigma_range_offset": c["sigma_range_offset"],
            "range_scale": c["range_scale"], "sigma_range_scale": c["sigma_range_scale"],
            "incidence_bias": c["incidence_bias"],
            "sigma_incidence_bias": c["sigma_incidence_bias"]}


def step_rows(steps: list[StepRecord]) -> list[StepRow]:
    """Each step attempt with its duration (s)."""
    return [
        {**s, "title": display.step_title(s["name"]),
         "duration_s": display.seconds_between(s["started_at"], s["finished_at"])}
        for s in steps
    ]


def final_calibration_dict(calibrations: list[CalibrationRecord]) -> CalibrationRecord | None:
    """The run's final calibration (accepted, else newest fine, else initial), as stored."""
    cals = calibrations
    for pick in ([c for c in cals if c["accepted"]], [c for c in cals if c["stage"] == "fine"],
                 list(cals)):
        if pick:
            return pick[-1]
    return None


def unit_serial(unit: str | None, data_dir: str | None, steps: Iterable[SerialStep]
                ) -> str | None:
    """The unit's serial: the run's own column (``unit``) when the database has one, else
    ``unit.json`` in the run folder (written by the web station), else the serial the lidar
    reported in preflight."""
    if unit:
        return str(unit)
    path = Path(data_dir or ".") / "unit.json"
    if data_dir and path.is_file():
        try:
            serial = json.loads(path.read_text(encoding="utf-8")).get("serial")
        except (OSError, ValueError):
            serial = None
        if serial:
            return str(serial)
    for s in steps:
        if s["name"] == "preflight" and s["status"] == StepStatus.PASSED:
            lidar = _mapping((s["result"] or {}).get("lidar"))
            if lidar.get("serial"):
                return str(lidar["serial"])
    return None


VERDICTS: dict[str, str] = {RunStatus.PASSED: "PASS", RunStatus.FAILED: "FAIL"}
"""The verdict the report shows for a run's status (others: the status in capitals)."""


def report_data(db: Database, run_id: int, *, views: bool = True) -> ReportData:
    """Everything the report shows, as plain data (also the web run page's JSON twin).

    ``views=False`` leaves out the 3D views (no recordings read).
    """
    from calstation.engine.frames import Extrinsics
    from calstation.storage.report import get_run, run_brief, run_summary

    with db.session("reading the run", read_only=True) as s:
        run: Run = get_run(s, run_id)
        summary = run_summary(run)
        brief = run_brief(run)
        recipe_text = run.recipe_text
    recipe = _limits(recipe_text)
    qa = recipe.qa if recipe is not None else None
    final = final_calibration_dict(summary["calibrations"])
    data: ReportData = {
        "run": {**brief, "qa_limits": summary["qa_limits"]},
        "serial": unit_serial(summary["unit_serial"], summary["data_dir"], summary["steps"]),
        "verdict": VERDICTS.get(summary["status"], summary["status"].upper()),
        "final": final,
        "calibrations": calibration_rows(summary["calibrations"]),
        "cube": summary["cube_check"],
        "cube_rows": cube_rows(summary["cube_check"], qa),
        "steps": step_rows(summary["steps"]),
        "artifacts": summary["artifacts"],
        "drift": _drift_of(summary),
        "qa": qa.model_dump() if qa is not None else None,
        "views": [],
        "figures": {},
        "accuracy": accuracy_of(final),
        "generated_at": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
    }
    data["partial"] = partial_note(summary, final)
    if final is not None:
        cost = _cost_figure(_iterated(summary["calibrations"], final))
        if cost is not None:
            data["figures"]["cost"] = cost
        where = _accuracy_figure(final)
        if where is not None:
            data["figures"]["accuracy"] = where
        residuals = range_residuals_of(_diagnostic(final, "joint"))
        if residuals is not None:
            data["figures"]["range_residuals"] = range_residuals_figure(residuals)
            data["range_residuals"] = range_residuals_text(residuals)
    if views and final is not None and recipe is not None:
        H = Extrinsics.from_dict(final["H"])
        radius = recipe.fixtures.platter.radius
        data["views"] = _views(summary["artifacts"], H, radius)
        hist = _histogram_figure([v for v in data["views"] if "figure" in v])
        if hist is not None:
            data["figures"]["residuals"] = hist
    return data


def partial_note(summary: RunSummary, final: CalibrationRecord | None) -> str | None:
    """What the figures of a run that did not pass show (None for a passed run): which
    calibration they are drawn with, that it is not accepted, and which recordings are
    incomplete."""
    if summary["status"] == RunStatus.PASSED or final is None:
        return None
    ended: dict[str, str] = {RunStatus.FAILED: "failed", RunStatus.ABORTED: "was aborted"}
    verdict = ended.get(summary["status"], "has not finished")
    partial = [a["kind"] for a in summary["artifacts"] if a["status"] != "complete"]
    scans = {a["kind"] for a in summary["artifacts"]}
    missing = [k for k in ("spin", "cube") if k not in scans]
    text = (f"This run {verdict}: no calibration was accepted. Its figures are drawn with its "
            f"{final['stage']} calibration ({final['strategy']}), which is NOT accepted"
            + (" — the initial H from the static scan, before any fine-tuning"
               if final["stage"] == "initial" else "") + ".")
    if partial:
        text += f" Partial recordings (the scan stopped early): {', '.join(partial)}."
    if missing:
        text += f" Not recorded: {', '.join(missing)}."
    return text


def views_data(db: Database, run_id: int) -> ViewsData:
    """The run's 3D views and residual histogram (what the web run page fetches after it
    painted): ``views`` (each with its figure, points and residual statistics), ``residuals``
    (the histogram figure or None), ``key`` (the final calibration and the run's status:
    the views change only with them)."""
    return _views_of(report_data(db, run_id))


def _views_of(data: ReportData) -> ViewsData:
    views: list[dict[str, object]] = [
        {k: ({kk: vv for kk, vv in v.items() if kk != "values"}
             if k == "residual" and isinstance(v, dict) else v) for k, v in view.items()}
        for view in data["views"]]
    final = data["final"]
    return {"views": views, "residuals": data["figures"].get("residuals"),
            "key": [final["id"] if final else None, data["run"]["status"]]}


VIEWS_FILE = "views.json"
"""The 3D views as the web run page fetches them, kept in the run folder with report.html."""


def stored_views(folder: Path, key: list[object]) -> str | None:
    """The run folder's :data:`VIEWS_FILE` as JSON text when it was written for ``key`` (the
    final calibration's id and the run's status), else None."""
    path = folder / VIEWS_FILE
    try:
        text = path.read_text(encoding="utf-8")
        head = json.loads(text[text.rindex(',"key":') + 7:-1])
    except (OSError, ValueError):
        return None
    return text if head == key else None


def _drift_of(summary: RunSummary) -> JSONObject | None:
    for s in reversed(summary["steps"]):
        if s["name"] == "report" and s["status"] == StepStatus.PASSED:
            drift = (s["result"] or {}).get("drift")
            return drift if isinstance(drift, dict) else None
    return None


def _views(artifacts: list[ArtifactRecord], H: Extrinsics, radius: float) -> list[View]:
    newest = {a["kind"]: a for a in artifacts}
    views: list[View] = []
    for kind, title, by in (("spin", "spin target (coloured by half-turn)", "half-turn"),
                            ("cube", "QA cube (coloured by residual to the local plane)",
                             "plane")):
        art = newest.get(kind)
        if art is None:
            continue
        path = Path(art["path"])
        if not path.is_file():
            views.append({"title": title, "error": f"recording missing: {path}"})
            continue
        if art["status"] not in (None, "complete"):
            title += " — PARTIAL recording: the scan stopped early"
        try:
            views.append(_cloud(path, H, radius, title, by))
        except CalstationError as exc:
            views.append({"title": title, "error": str(exc)})
    return views


# --- rendering -------------------------------------------------------------------------------
PLOTLY_FILE = "plotly-{version}.min.js"
"""plotly.js beside the run folders (``DATA_DIR/runs/``), written once and shared by every
run's ``report.html`` (``../plotly-….min.js``): a report stays small and opens offline."""


def plotly_file_name() -> str:
    from plotly import __version__

    return PLOTLY_FILE.format(version=__version__)


def figures_json(data: ReportData) -> str:
    """The report's figures as JSON for a ``<script type="application/json">`` block."""
    return json.dumps(
        {"views": [v.get("figure") for v in data["views"]], **data["figures"]},
        separators=(",", ":"),
    ).replace("</", "<\\/")  # inside <script>: "</" must not close it


def render_report(
    data: ReportData, *, plotly_src: str | None = None, nav: bool = False,
    nonce: str | None = None, views_src: str | None = None, **page: object,
) -> str:
    """The report as HTML. ``plotly_src`` is a URL of plotly.js; None inlines it. ``nav`` adds
    the web station's navigation bar and export links; ``nonce`` is put on its scripts and
    styles (the web station's Content-Security-Policy allows inline ones only with it);
    ``views_src``: a URL the page fetches its 3D views from (so it paints before they are
    computed); ``page``: the navigation bar's session fields (``csrf``, ``needs_login``,
    ``logged_in``)."""
    from calstation.storage.templating import environment

    template = environment().get_template("report.html")
    return template.render(
        d=data,
        params=list(PARAMS),
        figures_json=figures_json(data),
        nav=nav,
        plotly_inline=None if plotly_src else plotly_js(),
        plotly_src=plotly_src,
        plotly_name=plotly_file_name(),
        nonce=nonce,
        views_src=views_src,
        **page,
    )


def write_plotly_beside(runs_dir: Path) -> Path:
    """``runs_dir/plotly-<version>.min.js``, written when missing (atomically)."""
    path = runs_dir / plotly_file_name()
    text = plotly_js()
    if not path.is_file() or path.stat().st_size != len(text.encode("utf-8")):
        write_atomic(path, text, "plotly.js", make_parents=True)
    return path


def write_run_report(db: Database, run_id: int) -> Path:
    """Write ``report.html`` into the run's folder, plotly.js once beside the run folders;
    returns the report's path."""
    data = report_data(db, run_id)
    folder = Path(data["run"]["data_dir"])
    folder.mkdir(parents=True, exist_ok=True)
    write_plotly_beside(folder.parent)
    path = folder / "report.html"
    write_atomic(path, render_report(data, plotly_src=f"../{plotly_file_name()}"), "report")
    write_atomic(folder / VIEWS_FILE, json.dumps(_views_of(data), separators=(",", ":")),
                 "report's 3D views")
    return path
