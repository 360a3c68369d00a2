"""The lidar's range offset from its calibration certificate, combined with the station's own
measurement of it.

The station measures the range offset b with H from its fixtures (:mod:`calstation.engine.
fusion`), but only as far as their geometry tells b from where the lidar stands: moving the
lidar by b along its rays and shortening every range by b differ only by the spread of the rays'
directions over the fixture, so one cube turn gives b to about 0.1–0.3 mm, and H's translation
along the boresight, correlated with it, is known no better (docs/algorithms.md). A lidar whose
offset was measured on a range bench (its maker's certificate, or the plant's own
characterisation at a known distance) brings that measurement: the two are combined in
information form, a Kalman update on b whose gain moves H, the other range terms and their
covariance along their correlation with b (DESIGN §9: b is the same offset in the same
measurement equation on the bench and at the station).

A certificate that disagrees with the station's measurement beyond chance (the two-sided
p-value below :data:`~calstation.engine.fusion.CONSISTENCY_P`) is not combined: the certificate
is another lidar's, the lidar changed since, or a range error the model does not hold reads as
an offset on the station's fixtures. The calibration is then refused, naming both values.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.special import chdtrc

from calstation.engine.frames import PARAMETER_NAMES, Extrinsics
from calstation.engine.fusion import CONSISTENCY_P, kalman_update
from calstation.engine.rangemodel import RANGE_NAMES
from calstation.engine.result import CalibrationResult

OFFSET = "range_offset"


@dataclass(frozen=True)
class Certificate:
    """The lidar's range offset as its certificate states it: ``offset`` (m, > 0 reads long)
    and its 1σ ``sigma`` (m, > 0)."""

    offset: float
    sigma: float


def with_certificate(
    result: CalibrationResult, certificate: Certificate | None
) -> tuple[CalibrationResult, str | None]:
    """``result`` with the ``certificate``'s range offset combined into it: (the combined
    result, with ``diagnostics["certificate"]``; None) — or ``(result, why)`` when the two
    disagree beyond chance. ``result`` itself, with no failure, when there is no certificate or
    ``result`` did not measure the offset (no range model, or a spin target alone, which holds
    it: the station's refusal of such a result stands)."""
    record = result.diagnostics.get("covariance")
    measured, sigma_measured = result.range_offset, result.sigma_range_offset
    if (certificate is None or measured is None or sigma_measured is None
            or not math.isfinite(sigma_measured) or record is None
            or OFFSET not in record.get("parameters", [])):
        return result, None
    names = [str(n) for n in record["parameters"]]
    C = np.asarray(record["matrix"], dtype=np.float64)
    i = names.index(OFFSET)
    difference = certificate.offset - measured
    apart = difference / math.sqrt(sigma_measured**2 + certificate.sigma**2)
    said = {"offset": certificate.offset, "sigma": certificate.sigma, "measured": measured,
            "sigma_measured": sigma_measured, "sigma_apart": apart}
    if float(chdtrc(1, apart**2)) < CONSISTENCY_P:
        diagnostics = {**result.diagnostics, "certificate": {**said, "combined": False}}
        return replace(result, diagnostics=diagnostics), disagreement(said)
    gain, covariance = kalman_update(C, i, certificate.sigma**2)
    narrowed = gain * C[i, :]  # each variance's fall: C_kk − (C − gain·C_i)_kk
    x = {n: v for n, v in zip(PARAMETER_NAMES, result.H.as_vector(), strict=True)}
    x.update({n: getattr(result, n) for n in RANGE_NAMES if getattr(result, n) is not None})
    sigma = dict(result.sigma)
    sigma.update({n: getattr(result, f"sigma_{n}") for n in RANGE_NAMES
                  if getattr(result, n) is not None})
    for k, name in enumerate(names):
        # a term the covariance carries but the result does not estimate (the scale error it
        # did not measure, about zero: rangemodel.with_unmeasured_scale) keeps its value
        if name in x:
            x[name] = float(x[name] + gain[k] * difference)
        # the σ beyond the covariance (a bias bound in quadrature) stays as it was
        before = float(sigma.get(name, math.sqrt(max(float(C[k, k]), 0.0))))
        sigma[name] = math.sqrt(max(before**2 - float(narrowed[k]), 0.0))
    H = Extrinsics.from_vector(np.array([x[n] for n in PARAMETER_NAMES]))
    fields: dict[str, float | None] = {}
    for name in RANGE_NAMES:
        held = sigma.pop(name, None)
        if getattr(result, name) is not None:
            fields[name], fields[f"sigma_{name}"] = x[name], held
    diagnostics = {**result.diagnostics,
                   "covariance": {"parameters": names, "matrix": covariance.tolist()},
                   "certificate": {**said, "combined": True}}
    return replace(result, H=H, sigma=sigma, diagnostics=diagnostics).with_range(fields), None


def disagreement(said: dict[str, float]) -> str:
    """The refusal when the station's range offset and the certificate's disagree."""
    return (f"the lidar's range offset reads {said['measured'] * 1e3:+.3f} ± "
            f"{said['sigma_measured'] * 1e3:.3f} mm on the station's fixtures, but its "
            f"certificate says {said['offset'] * 1e3:+.3f} ± {said['sigma'] * 1e3:.3f} mm "
            f"(calibration.range_offset_certificate; {said['sigma_apart']:+.1f} σ apart): the "
            "certificate is another lidar's or in other units, the lidar has changed since it "
            "was measured, or a range error its model does not hold reads as an offset here "
            "(see the residuals against range and incidence in the report). Check the "
            "certificate against the lidar's serial number, or remove it to calibrate on the "
            "station's measurement alone")
