"""Numbers as people read them: the one formatter of every value calstation shows.

Storage, files and the JSON twins keep the stored units (metres, radians, seconds; the cube's
angles in degrees) and say which (:func:`units`); the pages, the terminal, the report and its
print show millimetres and degrees at one precision per quantity, through the functions here:

- :func:`number` — ``15.605 mm``, ``−0.3464°``; an em dash when there is no value;
- :func:`with_sigma` — ``15.605 ± 0.019 mm``, or ``not estimated`` for a parameter the run
  held rather than estimated (:func:`not_estimated`);
- :func:`duration` — ``0.4 s``, ``12 s``, ``2 min 05 s``, ``1 h 02 min``;
- :func:`when` — ``2026-11-23 14:05 UTC``;
- :func:`count` — ``1 turn``, ``3 turns``; :func:`scientific` — ``3.93 × 10⁻⁸``.

The web pages' scripts tick durations with a copy of :func:`duration` (``station.js``), held to
this one by a browser test.
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import TypeGuard

NOT_ESTIMATED = "not estimated"
"""What is shown for a parameter the run held instead of estimating (rx, the turntable's gauge;
the initial calibration's ry, which the L-target cannot tell)."""

MISSING = "—"
"""What is shown where there is no value."""

MINUS = "−"
"""The minus sign shown (U+2212: a line never breaks after it, unlike a hyphen)."""


@dataclass(frozen=True)
class Quantity:
    """How one quantity is stored and shown: ``stored`` unit (JSON, database), ``unit`` shown,
    ``factor`` from the stored to the shown unit, ``digits`` after the decimal point."""

    name: str
    label: str
    stored: str
    unit: str
    factor: float
    digits: int
    short: str = ""
    """a name short enough for a chart's axis or a table's column (default: ``name``)"""

    def shown(self, value: float) -> float:
        """``value`` (stored unit) in the shown unit."""
        return float(value) * self.factor

    @property
    def heading(self) -> str:
        """The short name with its unit, for a table's column or an axis: ``tx (mm)``."""
        return f"{self.short or self.name} ({self.unit})"

    @property
    def title(self) -> str:
        """The name in words with its unit: ``tx — translation along x (mm)``, ``cube face
        flatness, RMS (mm)``."""
        if self.name in H_PARAMS:
            return f"{self.name} — {self.label} ({self.unit})"
        return f"{self.label} ({self.unit})"


_DEG = math.degrees(1.0)


def _length(name: str, label: str, digits: int = 3, short: str = "") -> Quantity:
    return Quantity(name, label, "m", "mm", 1e3, digits, short)


def _angle(name: str, label: str, digits: int = 4) -> Quantity:
    return Quantity(name, label, "rad", "°", _DEG, digits)


def _degrees(name: str, label: str, digits: int = 3, short: str = "") -> Quantity:
    return Quantity(name, label, "deg", "°", 1.0, digits, short)


H_PARAMS = ("tx", "ty", "tz", "rx", "ry", "rz")
"""The calibration's parameters, in order."""

QUANTITIES: dict[str, Quantity] = {q.name: q for q in (
    _length("tx", "translation along x"),
    _length("ty", "translation along y"),
    _length("tz", "translation along z"),
    _angle("rx", "rotation about x"),
    _angle("ry", "tilt of the axis, rotation about y"),
    _angle("rz", "rotation about z"),
    _length("edge_error", "cube edge error, face fit", 2, "edge error"),
    _length("obb_error", "cube edge error, oriented box", 2, "OBB edge error"),
    _length("flatness_rms", "cube face flatness, RMS", 2, "flatness RMS"),
    _length("flatness_excess", "cube face flatness beyond the range noise, RMS", 2,
            "flatness beyond noise"),
    _length("edge", "cube edge", 2),
    _degrees("perpendicularity_deg", "cube perpendicularity", 3, "perpendicularity"),
    _degrees("twist_deg", "cube side-face twist", 3, "twist"),
    _length("predicted_error", "predicted reconstruction error", 3, "predicted error"),
    _length("axis_offset", "the axis's position across it", 3, "axis position"),
    _length("range_offset", "the lidar's range offset", 3, "range offset"),
    _length("residual", "residual", 2),
    _length("distance", "distance", 0),
    Quantity("time_offset", "lidar–encoder time offset", "s", "ms", 1e3, 3),
)}
"""Every quantity calstation shows, by the name its data carries."""


def quantity(name: str) -> Quantity:
    """The :class:`Quantity` called ``name``; the calibration's parameters and the cube's
    measures by their stored names."""
    try:
        return QUANTITIES[name]
    except KeyError:
        raise KeyError(f"{name!r} is not a quantity calstation shows "
                       f"({', '.join(QUANTITIES)})") from None


def units(names: Iterable[str]) -> dict[str, str]:
    """The stored unit of each of ``names``: what a JSON twin says beside its values."""
    return {n: quantity(n).stored for n in names}


def shown(name: str, value: float | None) -> float | None:
    """``value`` (stored unit) in the unit shown for ``name``; None stays None."""
    return None if value is None else quantity(name).shown(value)


def _finite(value: object) -> TypeGuard[int | float]:
    return isinstance(value, int | float) and not isinstance(value, bool) \
        and math.isfinite(float(value))


def plain(value: float, digits: int, signed: bool = False) -> str:
    """``value`` with ``digits`` decimals and a true minus sign (``+`` too when ``signed``)."""
    text = f"{value:+.{digits}f}" if signed else f"{value:.{digits}f}"
    if text.lstrip("+-").strip("0.") == "":  # no −0.000
        text = text.replace("-", "+" if signed else "")
    return text.replace("-", MINUS)


def number(name: str, value: object, *, signed: bool = False, unit: bool = True,
           digits: int | None = None) -> str:
    """``value`` (stored unit) of quantity ``name`` for people: ``15.605 mm``, ``0.3464°``;
    :data:`MISSING` when there is none. ``signed``: ``+``/``−`` always; ``unit=False`` leaves
    the unit out (a table whose heading names it)."""
    if not _finite(value):
        return MISSING
    q = quantity(name)
    text = plain(q.shown(value), q.digits if digits is None else digits, signed)
    return f"{text}{_unit(q) if unit else ''}"


def _unit(q: Quantity) -> str:
    return q.unit if q.unit == "°" else f" {q.unit}"


def not_estimated(value: object, sigma: object) -> bool:
    """Whether a calibration's parameter was held rather than estimated: it has no σ (None,
    or NaN from a stage that states none) and is zero (rx, the gauge, held at 0; the initial
    calibration's ry)."""
    no_sigma = sigma is None or (isinstance(sigma, float) and math.isnan(sigma))
    return no_sigma and (value is None or value == 0.0)


def sigma_text(name: str, sigma: object, unit: bool = True) -> str:
    """A 1σ as shown beside its value: ``± 0.019 mm``; empty without one."""
    if not _finite(sigma):
        return ""
    return f"± {number(name, sigma, unit=unit)}"


def with_sigma(name: str, value: object, sigma: object, *, unit: bool = True) -> str:
    """``15.605 ± 0.019 mm``; ``15.605 mm`` without σ; :data:`NOT_ESTIMATED` for a parameter
    held rather than estimated."""
    if not_estimated(value, sigma):
        return NOT_ESTIMATED
    if not _finite(sigma):
        return number(name, value, unit=unit)
    q = quantity(name)
    return (f"{number(name, value, unit=False)} ± {number(name, sigma, unit=False)}"
            f"{_unit(q) if unit else ''}")


def duration(seconds: object) -> str:
    """A duration as a person reads it: ``0.4 s``, ``12 s``, ``2 min 05 s``, ``1 h 02 min``;
    :data:`MISSING` without one."""
    if not _finite(seconds):
        return MISSING
    s = max(0.0, float(seconds))
    # halves round up, as the pages' copy (status.js) rounds them
    tenths = math.floor(s * 10.0 + 0.5)
    if tenths < 100:
        return f"{tenths // 10}.{tenths % 10} s"
    whole = math.floor(s + 0.5)
    if whole < 60:
        return f"{whole} s"
    if whole < 3600:
        return f"{whole // 60} min {whole % 60:02d} s"
    return f"{whole // 3600} h {whole % 3600 // 60:02d} min"


def seconds_between(start: object, end: object) -> float | None:
    """Seconds from ``start`` to ``end`` (datetimes or ISO-8601 texts); None without both."""
    if not start or not end:
        return None
    a = start if isinstance(start, dt.datetime) else dt.datetime.fromisoformat(str(start))
    b = end if isinstance(end, dt.datetime) else dt.datetime.fromisoformat(str(end))
    if (a.tzinfo is None) != (b.tzinfo is None):
        a, b = a.replace(tzinfo=dt.UTC), b.replace(tzinfo=dt.UTC)
    return (b - a).total_seconds()


def when(value: object, seconds: bool = False) -> str:
    """A stored time (ISO-8601 text or datetime, UTC) for people: ``2026-11-23 14:05 UTC``
    (``seconds``: ``14:05:09``); :data:`MISSING` when absent, the text itself when not a time."""
    if value is None or value == "":
        return MISSING
    try:
        t = value if isinstance(value, dt.datetime) else dt.datetime.fromisoformat(str(value))
    except ValueError:
        return str(value)
    if t.tzinfo is not None:
        t = t.astimezone(dt.UTC)
    return t.strftime("%Y-%m-%d %H:%M:%S" if seconds else "%Y-%m-%d %H:%M") + " UTC"


def count(n: int | float, noun: str, plural: str | None = None) -> str:
    """``1 turn``, ``3 turns``, ``1.5 turns``."""
    word = noun if n == 1 else (plural or f"{noun}s")
    return f"{n:g} {word}"


_SUPERSCRIPT = str.maketrans("0123456789-", "⁰¹²³⁴⁵⁶⁷⁸⁹⁻")


def scientific(value: object, digits: int = 3) -> str:
    """A number of any size in ``digits`` significant figures: ``0.0123``, ``3.93 × 10⁻⁸``
    (no ``e-08`` a line could break in); :data:`MISSING` without one."""
    if not _finite(value):
        return MISSING
    v = float(value)
    if v == 0.0 or 1e-3 <= abs(v) < 1e4:
        return f"{v:.{digits}g}".replace("-", MINUS)
    mantissa, exponent = f"{v:.{digits - 1}e}".split("e")
    return f"{mantissa.replace('-', MINUS)} × 10{str(int(exponent)).translate(_SUPERSCRIPT)}"


def percent(fraction: object, digits: int = 1) -> str:
    """``97.5 %`` of a fraction (0..1); :data:`MISSING` without one."""
    if not _finite(fraction):
        return MISSING
    return f"{100.0 * float(fraction):.{digits}f} %"


def megabytes(size_bytes: object) -> str:
    """A file's size: ``4.2 MB``, ``0.3 MB``; :data:`MISSING` without one."""
    if not _finite(size_bytes):
        return MISSING
    return f"{float(size_bytes) / 1e6:.1f} MB"


FIXTURE_NAMES: dict[str, str] = {
    "static_target": "L-shaped static target",
    "spin_target": "spin target",
    "qa_cube": "QA cube",
    "demo": "demonstration fixture",
}
"""What people call each fixture of a recipe (messages never show the recipe's keys)."""

STEP_TITLES: dict[str, str] = {
    "preflight": "preflight check",
    "place_static_target": "place the L-shaped static target",
    "static_scan": "static scan and initial calibration",
    "place_spin_target": "place the spin target",
    "spin_scan": "spin scan",
    "fine_tune": "fine-tuning",
    "place_qa_cube": "place the QA cube",
    "cube_scan": "QA cube scan and check",
    "report": "report",
}
"""What people call each step of a run."""


def fixture_name(fixture: str) -> str:
    """The name people use for ``fixture`` (a ``fixtures`` key)."""
    return FIXTURE_NAMES.get(fixture, fixture.replace("_", " "))


def step_title(step: str) -> str:
    """The name people use for ``step``."""
    return STEP_TITLES.get(step, step.replace("_", " "))


def time_left(elapsed_s: float, fraction: float) -> float | None:
    """Seconds still to go for work ``fraction`` (0..1) done in ``elapsed_s``, if the rest goes
    at the same pace; None before anything is done."""
    if not _finite(elapsed_s) or not _finite(fraction) or fraction <= 0.0:
        return None
    return max(0.0, float(elapsed_s) * (1.0 - min(1.0, float(fraction))) / float(fraction))


def progress_text(what: str, fraction: float, elapsed_s: float) -> str:
    """``simulating as designed, seed 2 — 25 %, 1 min 10 s so far, about 3 min 30 s left``
    (no estimate before anything is done)."""
    left = time_left(elapsed_s, fraction)
    text = f"{what} — {percent(fraction, 0)}, {duration(elapsed_s)} so far"
    return text + (f", about {duration(left)} left" if left is not None and fraction < 1.0
                   else "")
