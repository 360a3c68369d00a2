"""The lidar's range model (DESIGN §9): the systematic range errors estimated with H.

A lidar reports ``ρ_meas = (1 + k)·ρ_true + b + β(θ) + n``: a range offset ``b`` (metres; b > 0
reads long), a scale error ``k`` (dimensionless; 1e-3 is 0.1 %), an incidence bias β and noise n.
calstation estimates b, or b and k, together with H (``calibration.range_model``: ``none``,
``offset`` or ``offset+scale``) and corrects every return before it is reconstructed:
``ρ = (ρ_meas − b)/(1 + k)``, the point ``ρ·(sin α, cos α, 0)`` in L.

The incidence bias, β(θ) = c·(1/cos θ − 1) with θ the angle between the ray and the surface's
normal (c is the bias at 60°), is estimated with them (``calibration.incidence_bias``) where the
fits know the surfaces' normals — the spin target's local planes, the cube's faces, the platter
— because the periodicity cost sees the same facet at very different angles in its two
half-turns (about 25° and 65° for the default target at 45° of pitch): 1 mm of bias at 60°
moved an unmodelled axis by 0.7 mm on the simulator. A plain reconstruction, which knows no
normals, corrects b and k only.

Why it matters. To first order a range offset is the lidar moved by b along its boresight, so a
fit that does not model it puts b into H (ty by b, rz by about b/(2ρ) at 45° of pitch) and
still fits the data well; only the spread of the rays across the field of view (a zoom of
b/ρ across the rays, which turns planes that face the rays at 45° by ±b/(2ρ)) and the fixtures'
known sizes tell b from the mounting. A scale error is a scaled world — a larger platform
farther away looks the same — so only a known length (the QA cube's edge and height) sets it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Literal, cast

import numpy as np
from numpy.typing import NDArray

from calstation.engine.frames import PARAMETER_NAMES, FloatArray
from calstation.errors import CalibrationError

RangeModelName = Literal["none", "offset", "offset+scale"]
"""``calibration.range_model``: which range terms are estimated with H."""

RANGE_NAMES: tuple[str, ...] = ("range_offset", "range_scale", "incidence_bias")
"""The range model's parameters, after H's in every estimated vector."""

ESTIMATED_NAMES: tuple[str, ...] = PARAMETER_NAMES + RANGE_NAMES
"""Every parameter an estimate may carry, in the order of its vector: tx … rz (DESIGN §2), then
the range offset (m), the range scale error (dimensionless) and the incidence bias (m at 60°)."""

OFFSET, SCALE, INCIDENCE = (len(PARAMETER_NAMES) + i for i in range(3))
"""Indices of the range offset, the scale error and the incidence bias in an estimated vector."""

LEAST_COSINE = 0.2
"""Least cosine of a ray with a surface known only from local planes through its returns (the
spin target's) at which the incidence bias is computed (θ ≈ 78°): such a grazing return's normal
is too uncertain for the bias to be extrapolated further."""

LEAST_COSINE_KNOWN = 0.05
"""Least cosine of a ray with a surface known from its model — the QA cube's faces under the
box fitted to them, the platter under H — at which the known-size fit and the cube check compute
the incidence bias (θ ≈ 87°). The bias of DESIGN §9 grows as c·(1/cos θ − 1) up to grazing (the
simulator's does), and a side face that turns past the lidar is seen there: in the cube scan of
the sensor sweep's run 62 (0.5 mm at 60°) 3 % of the returns met their face beyond 78° and read
up to 7 mm long. Held at 78° (:data:`LEAST_COSINE`) the known-size fit read them as a larger
bias (0.615 ± 0.030 mm for 0.5 under the true H; 0.58 mm, 4.4σ high, in station runs, which
moved tx and tz by 1.5–2σ and set the spin target and the cube apart beyond chance in a quarter
of such runs), and the check's faces tilted (0.42° of perpendicularity under the true H and
range model, 1.38° at 2 mm of bias); to 87°: 0.497 ± 0.005 mm, and 0.14° and 0.18° (0.135° for
the same lidar without the bias). The faces' normals come from the cube's box, within about
0.5°, which moves a return at 87° by a sixth of c along its face's normal."""


def incidence_shape(
    cosine: NDArray[np.float64], least: float = LEAST_COSINE
) -> NDArray[np.float64]:
    """β(θ)/c = 1/cos θ − 1 for the (N,) cosines of rays with their surfaces (sign ignored),
    held at its value at the cosine ``least`` beyond it."""
    c = np.maximum(np.abs(np.asarray(cosine, dtype=np.float64)), least)
    out: NDArray[np.float64] = 1.0 / c - 1.0
    return out


def incidence_shape_slope(
    cosine: NDArray[np.float64], least: float = LEAST_COSINE
) -> NDArray[np.float64]:
    """d/d cosine of :func:`incidence_shape` (0 where it is held at ``least``)."""
    c = np.abs(cosine)
    out: NDArray[np.float64] = np.where(
        c > least, -np.sign(cosine) / np.maximum(c, least) ** 2, 0.0)
    return out


def estimated_indices(model: RangeModelName, incidence: bool = False) -> list[int]:
    """The indices (in :data:`ESTIMATED_NAMES`) of the range terms ``model`` estimates, with
    the incidence bias when ``incidence`` (and a range model is estimated at all)."""
    if model == "none":
        return []
    if model == "offset":
        out = [OFFSET]
    elif model == "offset+scale":
        out = [OFFSET, SCALE]
    else:
        raise CalibrationError(f"unknown range model {model!r}: none, offset or offset+scale")
    return [*out, INCIDENCE] if incidence else out


@dataclass(frozen=True)
class RangeModel:
    """The lidar's range offset ``offset`` (m), scale error ``scale`` (dimensionless) and
    incidence bias ``incidence`` (m at 60°)."""

    offset: float = 0.0
    scale: float = 0.0
    incidence: float = 0.0

    def __post_init__(self) -> None:
        if not all(math.isfinite(v) for v in (self.offset, self.scale, self.incidence)):
            raise CalibrationError(
                f"a range model must be finite, got offset {self.offset}, scale {self.scale}"
            )
        if not -0.5 < self.scale < 0.5:
            raise CalibrationError(f"a range scale error of {self.scale} is not a lidar's")

    @property
    def is_identity(self) -> bool:
        """True when it corrects nothing a reconstruction can correct (the incidence bias needs
        the surfaces' normals)."""
        return self.offset == 0.0 and self.scale == 0.0

    def ranges(self, measured: NDArray[np.float64]) -> NDArray[np.float64]:
        """The true ranges (m) of ``measured`` ones: ``(ρ_meas − b)/(1 + k)``."""
        out: NDArray[np.float64] = (np.asarray(measured, dtype=np.float64) - self.offset) / (
            1.0 + self.scale
        )
        return out

    def points(self, p_L: FloatArray) -> FloatArray:
        """(N, 3) returns in L (as measured, on their rays from the origin) corrected: each
        moved along its own ray to its corrected range."""
        return correct_points(p_L, self.offset, self.scale)

    def as_vector(self) -> FloatArray:
        """(3,) offset, scale, incidence bias: the tail of an estimated vector."""
        return np.array([self.offset, self.scale, self.incidence])

    @classmethod
    def from_vector(cls, x: FloatArray) -> RangeModel:
        """From an estimated vector of :data:`ESTIMATED_NAMES` (H's alone: the identity)."""
        v = np.asarray(x, dtype=np.float64).reshape(-1)
        if v.size == len(ESTIMATED_NAMES):
            return cls(float(v[OFFSET]), float(v[SCALE]), float(v[INCIDENCE]))
        if v.size == len(PARAMETER_NAMES):
            return cls()
        raise CalibrationError(f"an estimated vector has {len(ESTIMATED_NAMES)} values, "
                               f"got {v.size}")


IDENTITY = RangeModel()
"""The range model of an ideal lidar: nothing to correct."""


def correct_points(
    p_L: FloatArray, offset: float | FloatArray, scale: float, rho: FloatArray | None = None
) -> FloatArray:
    """(N, 3) returns in L moved along their rays: ``p·(1 − b/|p|)/(1 + k)``, ``offset`` b one
    value or one per return. A return at the origin (no range) stays there. ``rho``: the (N,)
    ranges |p| when already known (a fit that corrects the same returns at every evaluation)."""
    p = np.asarray(p_L, dtype=np.float64)
    b = np.asarray(offset, dtype=np.float64)
    if scale == 0.0 and not np.any(b):
        return p
    if rho is None:
        rho = np.linalg.norm(p, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        factor = np.where(rho > 0, (1.0 - b / rho) / (1.0 + scale), 0.0)
    out: FloatArray = p * factor[..., None]
    return out


def correct_vector(
    p_L: FloatArray, x: FloatArray, shape: FloatArray | None = None,
    rho: FloatArray | None = None,
) -> FloatArray:
    """:func:`correct_points` with the range terms of an estimated vector ``x`` (none when it
    holds H alone): the offset, and the incidence bias times ``shape`` (each return's
    :func:`incidence_shape`; none when None), then the scale error; ``rho`` the returns'
    ranges |p| when known."""
    if x.size <= OFFSET:
        return p_L
    offset: float | FloatArray = float(x[OFFSET])
    if shape is not None and float(x[INCIDENCE]) != 0.0:
        offset = offset + float(x[INCIDENCE]) * shape
    return correct_points(p_L, offset, float(x[SCALE]), rho)


def unit_rays(p_L: FloatArray) -> FloatArray:
    """(N, 3) the unit ray of each return in L (the lidar sits at the origin)."""
    out: FloatArray = p_L / np.maximum(np.linalg.norm(p_L, axis=1, keepdims=True), 1e-12)
    return out


def range_result_fields(
    x: FloatArray, sigma: dict[str, float], terms: list[int]
) -> dict[str, float | None]:
    """The range terms ``terms`` of an estimated vector ``x`` as a calibration result carries
    them (``range_offset``/``sigma_range_offset``, …), their σ popped from ``sigma`` (NaN: held,
    no σ of its own). The terms not estimated are left out (None in the result)."""
    out: dict[str, float | None] = {}
    for i in terms:
        name = ESTIMATED_NAMES[i]
        out[name] = float(x[i])
        out[f"sigma_{name}"] = sigma.pop(name, math.nan)
    return out


def describe(
    fields: Mapping[str, float | None], certificate: Mapping[str, object] | None = None
) -> str | None:
    """The lidar's range model for people, from a calibration's range fields (SI, None where not
    estimated; ``sigma_<name>`` beside each): "range offset +3.120 ± 0.100 mm, scale error
    +1240 ± 73 ppm, incidence bias +0.500 ± 0.020 mm at 60°", the terms not estimated left out;
    None when the calibration has no range model. With the ``certificate`` it combined (its
    ``diagnostics["certificate"]``, :mod:`calstation.engine.certificate`), the offset says where
    it came from."""
    def term(name: str, label: str, unit: float, digits: int, suffix: str) -> str | None:
        value = fields.get(name)
        if value is None:
            return None
        sigma = fields.get(f"sigma_{name}")
        text = f"{label} {float(value) * unit:+.{digits}f}"
        if sigma is None or not math.isfinite(float(sigma)):
            return f"{text} {suffix} (σ not estimated)"
        return f"{text} ± {float(sigma) * unit:.{digits}f} {suffix}"

    if fields.get("range_offset") is None:
        return None
    parts = [term("range_offset", "range offset", 1e3, 3, "mm"),
             term("range_scale", "scale error", 1e6, 0, "ppm"),
             term("incidence_bias", "incidence bias", 1e3, 3, "mm at 60°")]
    if certificate and certificate.get("combined"):
        said = {k: float(certificate[k])  # type: ignore[arg-type]
                for k in ("measured", "sigma_measured", "offset", "sigma")}
        parts[0] = (f"{parts[0]} (measured {said['measured'] * 1e3:+.3f} ± "
                    f"{said['sigma_measured'] * 1e3:.3f} mm, with the lidar's certificate "
                    f"{said['offset'] * 1e3:+.3f} ± {said['sigma'] * 1e3:.3f} mm)")
    return ", ".join(p for p in parts if p is not None)


def with_unmeasured_scale(
    t: FloatArray, sigma: Mapping[str, float], covariance: Mapping[str, object] | None,
    sigma_scale: float,
) -> tuple[dict[str, float], dict[str, object] | None]:
    """The σ and covariance of an estimate that did not measure the lidar's scale error, with
    the uncertainty that error leaves in it.

    A scale error k is a scaled world about the lidar (module docstring): a fit that holds k at
    0 finds the same rotation and the translation ``t·(1 + k)`` (``t`` the estimate's, metres),
    and every reconstruction with it is the world scaled by 1 + k. So with k of standard
    deviation ``sigma_scale`` (the lidar's stated scale uncertainty), the translation's error
    gains ``σ_k²·t·tᵀ``, the range correction's error in k is ``−k`` (variance σ_k²), and the
    two are correlated by ``−σ_k²·t``: the accuracy budget then predicts the scaled world's
    distortion, not the much larger one of a translation error alone. Returns ``sigma`` with
    tx, ty, tz widened, and the covariance record (``parameters``, ``matrix``) with
    ``range_scale`` appended (None stays None: a σ-only estimate gets no covariance).
    """
    s2 = float(sigma_scale) ** 2
    t = np.asarray(t, dtype=np.float64)
    widened = dict(sigma)
    for name, value in zip(("tx", "ty", "tz"), t, strict=True):
        if math.isfinite(widened.get(name, math.nan)):
            widened[name] = math.sqrt(widened[name] ** 2 + s2 * float(value) ** 2)
    if covariance is None or s2 == 0.0:
        return widened, None if covariance is None else dict(covariance)
    names = [str(n) for n in cast(list[object], covariance.get("parameters") or [])]
    if not names or "range_scale" in names:
        return widened, dict(covariance)
    C = np.asarray(covariance["matrix"], dtype=np.float64)
    n = len(names)
    out: FloatArray = np.zeros((n + 1, n + 1))
    out[:n, :n] = C
    out[n, n] = s2
    for axis, name in enumerate(("tx", "ty", "tz")):
        if name not in names:
            continue
        i = names.index(name)
        out[n, i] = out[i, n] = -s2 * float(t[axis])
        for other_axis, other in enumerate(("tx", "ty", "tz")):
            if other in names:
                out[i, names.index(other)] += s2 * float(t[axis]) * float(t[other_axis])
    return widened, {**covariance, "parameters": [*names, "range_scale"],
                     "matrix": out.tolist()}
