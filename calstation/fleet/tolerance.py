"""What a change of H is flagged above: a tolerance in the work volume (mm) or per parameter.

``--tolerance`` takes ``0.5`` (or ``0.5mm``, ``volume=0.5``): the work volume reconstructed with
the new H moves by more than 0.5 mm from where the stored H put it (after the best rigid
alignment: a rigid shift moves no point of an object relative to the others); and
``tx=0.2`` / ``ry=0.01`` (also ``tx=0.2mm``, ``ry=0.01deg``): a parameter changed by more than
that (translations in mm, rotations in degrees). Given several times, a unit is flagged when any
is exceeded. Without ``--tolerance`` each run's recipe's drift limits apply
(``qa.drift_translation``, ``qa.drift_rotation_deg``), per parameter, as between two runs of a
station. ty is not compared when the two calibrations fix the gauge differently (a shift of the
origin along the axis is a gauge choice, not a calibration difference), nor is rx (held at 0).

Tolerances are kept in SI (metres, radians) and applied to a stored comparison
(:func:`calstation.fleet.compare.compare`), so a campaign's flags can be recomputed when its
tolerance changes without computing anything again.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, field

from calstation.errors import FleetError
from calstation.storage.report import json_float

COMPARED = ("tx", "ty", "tz", "ry", "rz")
"""The parameters a tolerance applies to (rx is held at 0)."""

_SPEC = re.compile(
    r"^\s*(?:(?P<name>[a-z]+)\s*=\s*)?(?P<value>[0-9.eE+-]+)\s*(?P<unit>mm|deg|°)?\s*$"
)


@dataclass(frozen=True)
class Tolerance:
    """``volume_m``: the largest movement of the work volume (m), None: not checked;
    ``parameters``: the largest change per parameter (m or rad). Both empty: each run's
    recipe's drift limits."""

    volume_m: float | None = None
    parameters: dict[str, float] = field(default_factory=dict)

    @property
    def recipe_limits(self) -> bool:
        """Whether the recipes' drift limits apply (no tolerance was given)."""
        return self.volume_m is None and not self.parameters

    def as_dict(self) -> dict[str, object]:
        """As stored with the campaign (SI)."""
        return {"volume_m": self.volume_m, "parameters": dict(sorted(self.parameters.items()))}

    @classmethod
    def from_dict(cls, data: Mapping[str, object] | None) -> Tolerance:
        """The tolerance :meth:`as_dict` stored."""
        data = data or {}
        volume = data.get("volume_m")
        parameters = data.get("parameters") or {}
        if not isinstance(parameters, Mapping):
            raise TypeError(f"not a stored tolerance: {data!r}")
        return cls(None if volume is None else json_float(volume),
                   {str(k): json_float(v) for k, v in parameters.items()})

    def describe(self) -> str:
        """In display units: ``work volume 0.50 mm, tx 0.200 mm, ry 0.0100°``."""
        if self.recipe_limits:
            return "each run's recipe's drift limits (qa.drift_translation, qa.drift_rotation_deg)"
        parts = [] if self.volume_m is None else [f"work volume {self.volume_m * 1e3:.2f} mm"]
        for p, v in sorted(self.parameters.items()):
            parts.append(f"{p} {v * 1e3:.3f} mm" if p.startswith("t")
                         else f"{p} {math.degrees(v):.4f}°")
        return ", ".join(parts)


def parse_tolerance(specs: list[str] | tuple[str, ...]) -> Tolerance:
    """The tolerance of ``--tolerance`` values (see the module docstring); :class:`FleetError`
    naming a value that is not one."""
    volume: float | None = None
    parameters: dict[str, float] = {}
    for spec in specs:
        m = _SPEC.match(spec)
        name = (m.group("name") or "volume") if m else ""
        try:
            value = float(m.group("value")) if m else math.nan
        except ValueError:
            value = math.nan
        unit = (m.group("unit") or "") if m else ""
        if not m or not math.isfinite(value) or value <= 0 or name not in ("volume", *COMPARED) \
                or (unit == "mm" and name in ("ry", "rz")) \
                or (unit in ("deg", "°") and name not in ("ry", "rz")):
            raise FleetError(
                f"--tolerance {spec!r}: expected mm in the work volume (0.5, 0.5mm, volume=0.5) "
                "or a parameter's largest change (tx=0.2 in mm, ry=0.01 in degrees), above 0"
            )
        if name == "volume":
            volume = value * 1e-3
        elif name.startswith("t"):
            parameters[name] = value * 1e-3
        else:
            parameters[name] = math.radians(value)
    return Tolerance(volume, parameters)


def _numbers(value: object) -> dict[str, float | None]:
    """A stored mapping of numbers (None kept); empty when there is none."""
    if not isinstance(value, Mapping):
        return {}
    return {str(k): None if v is None else json_float(v) for k, v in value.items()}


def flags(comparison: Mapping[str, object], tolerance: Tolerance) -> list[str]:
    """Why ``comparison`` (:func:`calstation.fleet.compare.compare`) exceeds ``tolerance``, one
    sentence per exceeded limit (display units); empty when within."""
    out: list[str] = []
    diff = _numbers(comparison.get("difference"))
    skip_ty = bool(comparison.get("gauges_differ"))
    per: dict[str, float | None]
    if tolerance.recipe_limits:
        limits = _numbers(comparison.get("drift_limits"))
        per = {p: (limits.get("translation_m") if p.startswith("t")
                   else math.radians(limits.get("rotation_deg") or math.nan))
               for p in COMPARED}
        source = "the recipe's drift limit"
    else:
        per = dict(tolerance.parameters)
        source = "tolerance"
    for p in COMPARED:
        limit, d = per.get(p), diff.get(p)
        if limit is None or d is None or (p == "ty" and skip_ty) or not math.isfinite(limit):
            continue
        if abs(d) > limit:
            out.append(f"{p} changed by {d * 1e3:+.3f} mm ({source} {limit * 1e3:.3f} mm)"
                       if p.startswith("t") else
                       f"{p} changed by {math.degrees(d):+.4f}° ({source} "
                       f"{math.degrees(limit):.4f}°)")
    volume_change = comparison.get("change_in_work_volume_m")
    moved = None if volume_change is None else json_float(volume_change)
    if tolerance.volume_m is not None and moved is not None and moved > tolerance.volume_m:
        out.append(f"the work volume moves by {moved * 1e3:.3f} mm (tolerance "
                   f"{tolerance.volume_m * 1e3:.3f} mm)")
    return out
