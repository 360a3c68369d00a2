"""ry from the spin target and the QA cube together.

The periodicity cost sees ry weakly (docs/algorithms.md); the cube's side faces see it well: an
ry error twists them (:func:`calstation.cube.face_twist`). Every run scans both, so the station
combines them: the twist measured on the cube scan under the fine-tuned H is a measurement of
the ry correction, ``ry_cube = ry_fine + twist`` with its σ, and it updates the fine-tuning's
estimate through its covariance (a Kalman update), which also moves the parameters correlated
with ry (tz above all: the spin target fixes tz + ry·h at its own height h).

When the two disagree by more than :data:`CONSISTENCY_SIGMA` combined σ they are not combined:
one of them is wrong, and the cube check's twist limit reports it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from .frames import PARAMETER_NAMES, Extrinsics

CONSISTENCY_SIGMA = 3.0
"""Largest disagreement (in combined σ) between the two ry estimates that is still combined."""


@dataclass(frozen=True)
class JointRy:
    """The combined estimate: H and σ per parameter (SI), and how it was obtained."""

    H: Extrinsics
    sigma: dict[str, float]
    details: dict[str, Any]


def disagreement_sigma(sigma_ry: float, twist: float, twist_sigma: float) -> float:
    """How many combined σ the cube's ry correction ``twist`` (rad, 1σ ``twist_sigma``) lies
    from the fine-tuning's ry (1σ ``sigma_ry``)."""
    return abs(twist) / math.sqrt(sigma_ry**2 + twist_sigma**2)


def combine_with_cube(
    H: Extrinsics, covariance: dict[str, Any] | None, twist: float, twist_sigma: float
) -> JointRy | None:
    """Update H (with its ``covariance`` record: ``parameters`` names and ``matrix``, SI) with
    the cube's ry measurement ``H.ry + twist`` (rad) of 1σ ``twist_sigma`` (rad).

    None when there is nothing to combine (no covariance, ry not estimated, a twist that could
    not be measured) or when the two disagree by more than :data:`CONSISTENCY_SIGMA` σ.
    """
    if covariance is None or not (math.isfinite(twist) and math.isfinite(twist_sigma)):
        return None
    names = list(covariance.get("parameters", []))
    if "ry" not in names or twist_sigma <= 0:
        return None
    C = np.asarray(covariance["matrix"], dtype=np.float64)
    i = names.index("ry")
    var_ry = float(C[i, i])
    z = disagreement_sigma(math.sqrt(max(var_ry, 0.0)), twist, twist_sigma)
    details: dict[str, Any] = {
        "ry_spin_target": H.ry,
        "sigma_ry_spin_target": math.sqrt(max(var_ry, 0.0)),
        "ry_cube": H.ry + twist,
        "sigma_ry_cube": twist_sigma,
        "disagreement_sigma": z,
    }
    if z > CONSISTENCY_SIGMA:
        return None
    gain = C[:, i] / (var_ry + twist_sigma**2)
    x = H.as_vector()
    for k, name in enumerate(names):
        x[PARAMETER_NAMES.index(name)] += gain[k] * twist
    C_new = C - np.outer(gain, C[i, :])
    sigma = {n: math.nan for n in PARAMETER_NAMES}
    for k, name in enumerate(names):
        sigma[name] = math.sqrt(max(float(C_new[k, k]), 0.0))
    details["covariance"] = {"parameters": names, "matrix": C_new.tolist()}
    return JointRy(Extrinsics.from_vector(x), sigma, details)
