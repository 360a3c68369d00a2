"""The one result type of every calibration stage: H, its 1σ, cost, timings and diagnostics.

A :class:`CalibrationResult` is what the initial calibration and every fine-tuning strategy
return. It serialises to YAML/JSON (metres and radians, DESIGN §2) and exports the 4×4 transform
T_L_P, a quaternion and a URDF ``<origin>`` snippet.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, overload

import numpy as np
import yaml

from calstation.engine.frames import PARAMETER_NAMES, Extrinsics, FloatArray, as_float
from calstation.engine.rangemodel import RANGE_NAMES, RangeModel
from calstation.errors import CalibrationError, FrameError
from calstation.jsonvalue import JSONObject, JSONValue

RESULT_FORMAT = "calstation-calibration"
RESULT_VERSION = 1


@overload
def _plain(value: float | np.floating) -> float | None: ...


@overload
def _plain(value: object) -> JSONValue: ...


def _plain(value: object) -> JSONValue:
    """Numpy scalars/arrays and tuples → plain Python for YAML/JSON; NaN/inf → None (and any
    other object, which YAML and JSON could not hold, its text)."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        items: list[object] = value.tolist()
        return _plain(items)
    if isinstance(value, (np.floating, float)):
        f = float(value)
        return f if math.isfinite(f) else None
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (np.bool_,)):
        return bool(value)
    if value is None or isinstance(value, str | int):
        return value
    return str(value)


def _optional(value: float | None) -> float | None:
    return None if value is None else _plain(float(value))


def _number(d: Mapping[str, object], key: str, unit: str = "") -> float | None:
    """The optional finite number ``d[key]`` (of ``unit``, for messages), None when absent or
    null."""
    value = d.get(key)
    if value is None:
        return None
    what = f"a number of {unit}" if unit else "a number"
    try:
        out = as_float(value)
    except (TypeError, ValueError):
        raise CalibrationError(
            f"calibration field '{key}': expected {what}, got {value!r}"
        ) from None
    if not math.isfinite(out):
        raise CalibrationError(f"calibration field '{key}': expected a finite {what[2:]}")
    return out


def _seconds(d: Mapping[str, object], key: str) -> float | None:
    """The optional finite number ``d[key]`` (seconds), None when absent or null."""
    return _number(d, key, "seconds")


RANGE_FIELDS: tuple[str, ...] = tuple(
    f for name in RANGE_NAMES for f in (name, f"sigma_{name}")
)
"""The range model's fields of a result, a summary and a stored calibration (DESIGN §9)."""


@dataclass(frozen=True)
class CalibrationResult:
    """A calibration H with its uncertainty and how it was obtained.

    - ``H``: pose of P in L (metres, radians), rx held at 0.
    - ``sigma``: 1σ per parameter name (tx … rz), metres / radians; NaN when the stage does not
      estimate it (e.g. ry in the initial calibration, ty under the ``ty`` gauge).
    - ``cost``: the stage's final cost (its own units, documented per strategy).
    - ``iterations``: outer iterations (or function evaluations) used.
    - ``strategy``: ``"initial"``, ``"periodicity"``, ``"shape"``, or a plugin's name.
    - ``timings``: seconds per named phase.
    - ``diagnostics``: free-form details (matches per iteration, gauge, segments seen, …).
    - ``encoder_latency_s`` / ``sigma_encoder_latency_s``: the lidar–encoder time offset
      (encoder time minus lidar time, s) and its 1σ, when the spin scan had a second pass to
      estimate it (:mod:`calstation.engine.timeoffset`); reconstruction then uses it in place of the
      recording's configured latency. None otherwise.
    - ``range_offset`` / ``sigma_range_offset`` (m), ``range_scale`` / ``sigma_range_scale``
      (dimensionless) and ``incidence_bias`` / ``sigma_incidence_bias`` (m at 60°): the lidar's
      range model estimated with H (DESIGN §9, :mod:`calstation.engine.rangemodel`); every
      reconstruction corrects the ranges with the offset and the scale error. None when not
      estimated.
    """

    H: Extrinsics
    sigma: dict[str, float]
    cost: float
    iterations: int
    strategy: str
    timings: dict[str, float] = field(default_factory=dict)
    diagnostics: dict[str, Any] = field(default_factory=dict)  # Any: free-form, see above
    encoder_latency_s: float | None = None
    sigma_encoder_latency_s: float | None = None
    range_offset: float | None = None
    sigma_range_offset: float | None = None
    range_scale: float | None = None
    sigma_range_scale: float | None = None
    incidence_bias: float | None = None
    sigma_incidence_bias: float | None = None

    @property
    def range_model(self) -> RangeModel:
        """The range correction every reconstruction with this calibration applies (none when
        the range model was not estimated)."""
        return RangeModel(self.range_offset or 0.0, self.range_scale or 0.0,
                          self.incidence_bias or 0.0)

    def with_range(self, fields: Mapping[str, float | None]) -> CalibrationResult:
        """The same result with the range model's ``fields`` (:data:`RANGE_FIELDS`) given."""
        unknown = set(fields) - set(RANGE_FIELDS)
        if unknown:
            raise CalibrationError(f"not a range model field: {', '.join(sorted(unknown))}")
        return replace(
            self,
            range_offset=fields.get("range_offset", self.range_offset),
            sigma_range_offset=fields.get("sigma_range_offset", self.sigma_range_offset),
            range_scale=fields.get("range_scale", self.range_scale),
            sigma_range_scale=fields.get("sigma_range_scale", self.sigma_range_scale),
            incidence_bias=fields.get("incidence_bias", self.incidence_bias),
            sigma_incidence_bias=fields.get("sigma_incidence_bias", self.sigma_incidence_bias),
        )

    def range_fields(self) -> dict[str, float | None]:
        """``range_offset``, ``sigma_range_offset`` (m), ``range_scale``, ``sigma_range_scale``,
        ``incidence_bias``, ``sigma_incidence_bias`` (m at 60°): as :meth:`summary` and the
        stored calibration carry them (None: not estimated)."""
        return {name: _optional(getattr(self, name)) for name in RANGE_FIELDS}

    # --- serialisation -----------------------------------------------------------------------
    def to_dict(self) -> JSONObject:
        """A plain mapping (YAML/JSON ready): H and sigma in metres and radians."""
        return {
            "format": RESULT_FORMAT,
            "version": RESULT_VERSION,
            "strategy": self.strategy,
            "H": {**self.H.as_dict()},
            "sigma": {n: _plain(float(self.sigma.get(n, math.nan))) for n in PARAMETER_NAMES},
            "cost": _plain(float(self.cost)),
            "iterations": int(self.iterations),
            "encoder_latency_s": _optional(self.encoder_latency_s),
            "sigma_encoder_latency_s": _optional(self.sigma_encoder_latency_s),
            **self.range_fields(),
            "timings": _plain(dict(self.timings)),
            "diagnostics": _plain(dict(self.diagnostics)),
            "T_L_P": self.as_matrix().tolist(),
            "quaternion_xyzw": self.as_quaternion().tolist(),
        }

    @classmethod
    def from_dict(cls, d: object) -> CalibrationResult:
        """Inverse of :meth:`to_dict`; :class:`CalibrationError` names what is missing or wrong."""
        if not isinstance(d, dict):
            raise CalibrationError(f"a calibration must be a mapping, got {type(d).__name__}")
        if "H" not in d:
            raise CalibrationError("calibration is missing 'H' (tx, ty, tz, rx, ry, rz)")
        try:
            H = Extrinsics.from_dict(d["H"])
        except FrameError as exc:
            raise CalibrationError(f"calibration field 'H': {exc}") from None
        raw_sigma = d.get("sigma") or {}
        sigma = {
            n: math.nan if raw_sigma.get(n) is None else float(raw_sigma[n])
            for n in PARAMETER_NAMES
        }
        cost = d.get("cost")
        latency = _seconds(d, "encoder_latency_s")
        ranges: dict[str, float | None] = {}
        for name in RANGE_NAMES:
            value = _number(d, name)
            ranges[name] = value
            ranges[f"sigma_{name}"] = None if value is None else _number(d, f"sigma_{name}")
        return cls(
            H=H,
            sigma=sigma,
            cost=math.nan if cost is None else float(cost),
            iterations=int(d.get("iterations", 0)),
            strategy=str(d.get("strategy", "unknown")),
            timings={str(k): float(v) for k, v in (d.get("timings") or {}).items()},
            diagnostics=dict(d.get("diagnostics") or {}),
            encoder_latency_s=latency,
            sigma_encoder_latency_s=(
                None if latency is None else _seconds(d, "sigma_encoder_latency_s")
            ),
            **ranges,
        )

    def to_yaml(self) -> str:
        """YAML text of :meth:`to_dict`."""
        return yaml.safe_dump(self.to_dict(), sort_keys=False)

    def to_json(self) -> str:
        """JSON text of :meth:`to_dict` (NaN written as null)."""
        return json.dumps(self.to_dict(), indent=2)

    def save(self, path: str | Path, what: str = "calibration file") -> Path:
        """Write YAML (``.yaml``/``.yml``) or JSON (any other suffix), whole or not at all
        (:func:`calstation.atomic.write_atomic`: a folder, device or FIFO at ``path`` is refused,
        and on a failure the file there is as it was); the path written."""
        from calstation.atomic import write_atomic

        p = Path(path)
        text = self.to_yaml() if p.suffix.lower() in (".yaml", ".yml") else self.to_json()
        return write_atomic(p, text, what)

    @classmethod
    def load(cls, path: str | Path) -> CalibrationResult:
        """Read a file written by :meth:`save` (YAML or JSON)."""
        from calstation.yamlsafe import read_text_file

        p = Path(path)
        try:  # a regular file of bounded size only (a FIFO would block forever)
            text = read_text_file(p, "calibration file", 10_000_000)
        except ValueError as exc:
            raise CalibrationError(f"{p}: {exc}") from None
        try:
            data = yaml.safe_load(text)  # JSON is YAML
        except yaml.YAMLError as exc:
            raise CalibrationError(f"{p}: not a YAML/JSON calibration file: {exc}") from None
        try:
            return cls.from_dict(data)
        except CalibrationError as exc:
            raise CalibrationError(f"{p}: {exc}") from None

    # --- exports -------------------------------------------------------------------------------
    def as_matrix(self) -> FloatArray:
        """4×4 homogeneous T_L_P (P points → L)."""
        return self.H.as_matrix()

    def as_quaternion(self) -> FloatArray:
        """Rotation of P in L as a unit quaternion (x, y, z, w), w ≥ 0."""
        return self.H.as_quaternion()

    def urdf_origin(self) -> str:
        """URDF ``<origin xyz=… rpy=…/>`` of P in L."""
        return self.H.urdf_origin()

    def summary(self) -> dict[str, object]:
        """The flat mapping ``calstation calibrate --json`` prints.

        tx, ty, tz (m), rx, ry, rz (rad), ``sigma_<name>`` for each, strategy, cost, iterations,
        ``encoder_latency_s`` and its ``sigma_encoder_latency_s`` (s, None when not estimated),
        ``range_offset`` and ``sigma_range_offset`` (m), ``range_scale`` and
        ``sigma_range_scale``, ``incidence_bias`` and ``sigma_incidence_bias`` (m at 60°)
        (DESIGN §9; None when not estimated).
        """
        out: dict[str, object] = {n: float(getattr(self.H, n)) for n in PARAMETER_NAMES}
        for n in PARAMETER_NAMES:
            out[f"sigma_{n}"] = _plain(float(self.sigma.get(n, math.nan)))
        out["sigma"] = {n: out[f"sigma_{n}"] for n in PARAMETER_NAMES}
        out["strategy"] = self.strategy
        out["cost"] = _plain(float(self.cost))
        out["iterations"] = int(self.iterations)
        out["encoder_latency_s"] = _optional(self.encoder_latency_s)
        out["sigma_encoder_latency_s"] = _optional(self.sigma_encoder_latency_s)
        out.update(self.range_fields())
        out["timings"] = _plain(dict(self.timings))
        return out
