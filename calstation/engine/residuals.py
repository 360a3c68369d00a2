"""What a fit's residuals say about the lidar's range errors that its range model does not hold.

After a fit with the range model (DESIGN §9), each return's residual is read as a range error:
how much longer (positive) or shorter the return reads than the fitted surface along its ray.
A lidar that the model describes leaves residuals that are noise, the same at every range,
incidence angle and azimuth. A trend against one of them is an error the model does not hold:

- against the **range**: a scale error the model does not estimate (``offset`` alone), or a
  range error that is not linear in the range;
- against the **incidence angle** (between the ray and the surface's normal): an incidence bias
  the model does not estimate, or one of another shape than c·(1/cos θ − 1), or surfaces of
  different finish (reflectivity) seen at different angles;
- against the **azimuth** (the ray's angle in the scan plane): a range error that varies
  across the field of view, which no range model holds (a window, the lidar's own encoder).

:func:`residual_trends` bins the residuals by each quantity (equal counts) and gives each bin's
median with its σ; a trend is **significant** when its bins differ by more than both
:data:`FLOOR_M` and :data:`SIGNIFICANCE` times their σ. :func:`unmodelled` says the significant
ones in words, for the refusal advice and the report.

A range error the model does hold still has its uncertainty: when the cube check fails, what the
estimated terms' σ (and the incidence bias's model error) can do to the failed figures
(:func:`calstation.engine.joint.range_responses`) is said by :func:`in_check`, with the
trends, so that a cube the lidar's ranges may have put out of square is not blamed on its
squareness alone.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TypedDict

import numpy as np

from calstation.engine.frames import FloatArray

BINS = 6
"""Bins (equal counts) per quantity."""
FLOOR_M = 5e-5
"""A difference between bins below this (m) is not called a trend, however well measured."""
SIGNIFICANCE = 3.0
"""How many σ the trend's slope must be from 0 to call it one, its σ widened by the bins'
scatter about the line (the returns of one surface are not independent)."""
LEAST_PER_BIN = 30
"""A bin with fewer returns is left out."""

UNITS = {"range": ("m", 1.0), "incidence": ("°", math.degrees(1.0)),
         "azimuth": ("°", math.degrees(1.0))}
"""The quantities, their unit for people and the factor from SI (radians to degrees)."""



class TrendRecord(TypedDict):
    """One quantity's trend as a fit's diagnostics keep it (JSON-ready)."""

    unit: str
    centre: list[float]
    median_m: list[float]
    sigma_m: list[float]
    count: list[int]
    spread_m: float
    z: float
    significant: bool


def residual_trends(
    range_error_m: FloatArray, quantities: Mapping[str, FloatArray]
) -> dict[str, TrendRecord]:
    """Per quantity (``range`` m, ``incidence`` rad, ``azimuth`` rad; one value per return):
    ``centre`` of each bin (m or degrees), ``median_m`` and ``sigma_m`` (the bin's median range
    error and its σ, metres), ``count``, ``spread_m`` (the trend's line across the bins: the range
    error at the last bin less the first's), ``z`` (its slope over the slope's σ) and
    ``significant`` (see the module docstring). Non-finite returns are left out."""
    error = np.asarray(range_error_m, dtype=np.float64)
    out: dict[str, TrendRecord] = {}
    for name, values in quantities.items():
        v = np.asarray(values, dtype=np.float64)
        keep = np.isfinite(v) & np.isfinite(error)
        if np.count_nonzero(keep) < 2 * LEAST_PER_BIN:
            continue
        out[name] = _binned(name, v[keep], error[keep])
    return out


def _binned(name: str, values: FloatArray, error: FloatArray) -> TrendRecord:
    """One quantity's :func:`residual_trends` record: equal-width bins between the 1st and
    99th percentiles, each bin's median, and the line through them weighted by their σ (its
    slope's σ widened by the scatter about the line when that exceeds the σ: a wiggle is not
    a trend)."""
    lo, hi = np.percentile(values, [1.0, 99.0])
    edges = np.linspace(lo, hi, BINS + 1)
    where = np.clip(np.searchsorted(edges, values, side="right") - 1, 0, BINS - 1)
    unit, factor = UNITS.get(name, ("", 1.0))
    centres, medians, sigmas, counts = [], [], [], []
    for b in range(BINS):
        e = error[(where == b) & (values >= lo) & (values <= hi)]
        if e.size < LEAST_PER_BIN:
            continue
        median = float(np.median(e))
        mad = float(np.median(np.abs(e - median))) * 1.4826
        centres.append(0.5 * float(edges[b] + edges[b + 1]) * factor)
        medians.append(median)
        sigmas.append(max(1.2533 * mad / math.sqrt(e.size), 1e-9))  # σ of a median
        counts.append(int(e.size))
    x = [_shape(name, c) for c in centres]
    slope, sigma_slope = _line(x, medians, sigmas)
    span = slope * (x[-1] - x[0]) if x else 0.0
    significant = (math.isfinite(sigma_slope) and abs(span) > FLOOR_M
                   and abs(slope) > SIGNIFICANCE * sigma_slope)
    return {"unit": unit, "centre": centres, "median_m": medians, "sigma_m": sigmas,
            "count": counts, "spread_m": span,
            "z": abs(slope) / sigma_slope if sigma_slope > 0 else 0.0,
            "significant": bool(significant)}


def _shape(name: str, centre: float) -> float:
    """What a trend is a line in: the incidence bias's own shape, 1/cos θ − 1 (θ in degrees;
    the rays that meet a surface obliquely read much longer than the rest), else the
    quantity."""
    if name == "incidence":
        return 1.0 / max(math.cos(math.radians(centre)), 0.2) - 1.0
    return centre


def _line(x: list[float], y: list[float], sigma: list[float]) -> tuple[float, float]:
    """The slope of the weighted line through (x, y) and its σ, widened by the Birge ratio
    (√(χ²/dof)) when the points scatter about the line more than their σ."""
    if len(x) < 3:
        return 0.0, math.inf
    X = np.column_stack([np.ones(len(x)), np.asarray(x)])
    w = 1.0 / np.asarray(sigma)
    coef, *_ = np.linalg.lstsq(X * w[:, None], np.asarray(y) * w, rcond=None)
    chi2 = float(np.sum(((np.asarray(y) - X @ coef) * w) ** 2))
    cov = np.linalg.inv((X * w[:, None]).T @ (X * w[:, None]))
    birge = max(1.0, math.sqrt(chi2 / (len(x) - 2)))
    return float(coef[1]), math.sqrt(float(cov[1, 1])) * birge


def unmodelled(trends: Mapping[str, TrendRecord]) -> list[str]:
    """The significant trends of :func:`residual_trends` in words, each with what it suggests:
    "returns read 0.21 mm longer at 72° of incidence than at 18° (a bias with the angle …)"."""
    words = []
    for name, trend in trends.items():
        if not trend["significant"]:
            continue
        centres, span = trend["centre"], trend["spread_m"]
        longer, shorter = (centres[-1], centres[0]) if span > 0 else (centres[0], centres[-1])
        head = (f"returns read {abs(span) * 1e3:.2f} mm longer at {_at(name, longer)} "
                f"{_of(name)}than at {_at(name, shorter)}")
        words.append(f"{head} ({_suggests(name, span / (centres[-1] - centres[0]))})")
    return words


def _at(name: str, centre: float) -> str:
    """A bin's centre for people: metres of range, degrees of incidence or azimuth."""
    if name == "range":
        return f"{centre:.2f} m"
    return f"{centre:+.0f}°" if name == "azimuth" else f"{centre:.0f}°"


def _of(name: str) -> str:
    return {"range": "of range ", "incidence": "of incidence ", "azimuth": "of azimuth "}.get(
        name, "")


def _suggests(name: str, slope: float) -> str:
    """What a trend against ``name`` suggests (``slope``: m per unit of the quantity)."""
    if name == "range":
        return (f"a range scale error of about {slope * 1e6:+.0f} ppm the range model does not "
                "hold: calibration.range_model: offset+scale")
    if name == "incidence":
        return ("a bias with the angle the rays meet the surfaces: calibration.incidence_bias: "
                "estimate, or fixtures of one finish")
    return ("a range error that varies across the lidar's field of view, which no range model "
            "holds: check the lidar's window, or place the fixtures at the centre of its view")


class FigureResponse(TypedDict):
    """One failed figure of the cube check (``perpendicularity_deg`` in degrees,
    ``edge_error`` or ``flatness_excess`` in metres): its ``value``, its ``limit``, and the
    figure ``at`` the range term moved down and up by its step."""

    value: float
    limit: float
    at: list[float]


class TermResponse(TypedDict):
    """How the cube check's failed figures follow one range term (``incidence_bias`` m at 60°,
    ``range_offset`` m or ``range_scale``): its estimate ``value`` and ``sigma``, the
    ``model_error`` beside its σ (the incidence bias's shape), the ``step`` it was moved by
    (the two in quadrature) and each failed figure's response."""

    name: str
    value: float
    sigma: float
    model_error: float
    step: float
    figures: dict[str, FigureResponse]


FIGURE_WORDS = {"perpendicularity_deg": ("the perpendicularity", "°", 1.0, 3),
                "edge_error": ("the face-fit edge error", " mm", 1e3, 2),
                "flatness_excess": ("the flatness beyond the noise", " mm", 1e3, 2)}
"""A failed figure for people: its name, unit, factor from SI and decimals (as the check's
failures give it)."""

TERM_WORDS = {"incidence_bias": ("incidence bias", " mm", " at 60°", 1e3, 3),
              "range_offset": ("range offset", " mm", "", 1e3, 3),
              "range_scale": ("scale error", " ppm", "", 1e6, 0)}
"""A range term for people: its name, unit, what its value is of, factor from SI and
decimals."""


def in_check(responses: list[TermResponse], trends: Mapping[str, TrendRecord]) -> str | None:
    """What the lidar's range error may do to a cube check that failed, in words, or None when
    there is nothing to say: each clear range term's uncertainty and how far it moves the
    failed figures (:func:`calstation.engine.joint.range_responses`), whether that could bring
    them within their limits, and what would tell the lidar's range error from the cube's
    shape; and the significant residual trends (:func:`unmodelled`)."""
    seen = unmodelled(trends)
    if not responses:
        if not seen:
            return None
        return ("the lidar's range error is not what its range model says, and may be what the "
                f"cube check sees — on the cube's faces, {'; '.join(seen)}")
    within = any(min(f["at"]) <= f["limit"] for r in responses for f in r["figures"].values())
    verdict = ("within one range term's uncertainty the cube would pass, so the check cannot "
               "tell the unit's shape from the lidar's range error" if within
               else "no one term's uncertainty brings it within its limit")
    said = (f"the lidar's range error may be part of what the cube check sees: "
            f"{'; '.join(_term(r) for r in responses)} — {verdict}. {_separate(responses)}")
    if seen:
        said += (" Its range error is also not what its range model says — on the cube's "
                 f"faces, {'; '.join(seen)}")
    return said


def _term(r: TermResponse) -> str:
    """One range term's uncertainty and the failed figures' response to it."""
    label, unit, of, factor, digits = TERM_WORDS[r["name"]]
    why = "its σ"
    if r["model_error"] > 0:
        why = f"its σ and {r['model_error'] * factor:.{digits}f}{unit} for the bias's shape"
    head = (f"its {label}, {r['value'] * factor:+.{digits}f} ± {r['sigma'] * factor:.{digits}f}"
            f"{unit}{of}, moved by {r['step'] * factor:.{digits}f}{unit} ({why}),")
    moves = []
    for name, f in r["figures"].items():
        what, funit, ffactor, fdigits = FIGURE_WORDS[name]
        by = max(abs(a - f["value"]) for a in f["at"])
        lower = 0 if f["at"][0] <= f["at"][1] else 1  # the term moved down, or up
        if f["at"][lower] >= f["value"]:
            moves.append(f"moves {what} by {by * ffactor:.{fdigits}f}{funit}, up either way")
            continue
        term_at = r["value"] + (2 * lower - 1) * r["step"]
        state = "within" if f["at"][lower] <= f["limit"] else "still over"
        moves.append(f"moves {what} by {by * ffactor:.{fdigits}f}{funit} (down to "
                     f"{f['at'][lower] * ffactor:.{fdigits}f}{funit} at "
                     f"{term_at * factor:+.{digits}f}{unit}, {state} its "
                     f"{f['limit'] * ffactor:.{fdigits}f}{funit} limit)")
    return f"{head} {' and '.join(moves)}"


def _separate(responses: list[TermResponse]) -> str:
    """What would tell the lidar's range terms from the cube's shape, from what each term's
    uncertainty came from: more turns narrow a σ, not the incidence bias's shape (a model);
    another placement of the cube meets its faces at other angles and ranges, which moves a
    range error's effect on the check and not the cube's shape; the lidar's own figures
    compare with the estimates."""
    say = []
    if any(r["sigma"] >= r["model_error"] for r in responses):
        say.append("more cube turns (steps.cube_scan.max_revolutions), which narrow the σ")
    say.append("the cube re-seated at another yaw, which meets its faces at other angles and "
               "ranges: a range error's effect on the check moves with it, the cube's shape "
               "does not")
    names = {r["name"] for r in responses}
    if "incidence_bias" in names:
        say.append("the incidence bias from the lidar's datasheet, to compare with the estimate")
    if names & {"range_offset", "range_scale"}:
        say.append("the lidar's range offset and scale from its calibration certificate, to "
                   "compare with the estimates")
    shape = [r for r in responses if r["model_error"] > r["sigma"]]
    head = ("More turns would not narrow the incidence bias's shape, most of its uncertainty. "
            if shape else "")
    return f"{head}What would tell them apart: " + "; ".join(say) + "."
