"""The combination of the spin target's and the cube's estimates (calstation.engine.fusion)."""

from __future__ import annotations

import math

import numpy as np

from calstation.engine.fusion import Estimate, fuse
from calstation.engine.rangemodel import ESTIMATED_NAMES

SPIN = ("tx", "tz", "ry", "rz")
FOLLOWS = {"incidence_bias": {"tx": 0.89, "tz": 0.012, "ry": 0.20, "rz": -0.57}}
"""How a spin target's estimate follows an incidence bias it holds (per metre of bias): a
station run's figures on the simulator (0.5 mm at 60°, 1 mm of noise, 1000 lines/s)."""


def _estimate(values: dict[str, float], sigmas: dict[str, float],
              follows: dict[str, dict[str, float]] | None = None) -> Estimate:
    vector = np.zeros(len(ESTIMATED_NAMES))
    for name, value in values.items():
        vector[ESTIMATED_NAMES.index(name)] = value
    names = tuple(n for n in ESTIMATED_NAMES if n in sigmas)
    return Estimate(vector, names, np.diag([sigmas[n] ** 2 for n in names]), follows or {})


def test_model_error_is_independent_per_parameter() -> None:
    spin = _estimate({}, dict.fromkeys(SPIN, 5e-5), FOLLOWS)
    size = 0.2 * 5e-4
    widened = spin.with_model_error("incidence_bias", size)
    expected = np.diag([5e-5 ** 2 + (FOLLOWS["incidence_bias"][n] * size) ** 2 for n in SPIN])
    assert np.allclose(widened.covariance, expected, rtol=1e-12, atol=0.0)
    assert spin.with_model_error("range_scale", size) is spin


def test_another_fixtures_tx_does_not_tell_how_far_rz_missed() -> None:
    """What the incidence correction missed on a station run of the simulator: tx by about 28 %
    of the bias's whole effect, rz by about 70 % of it with the opposite sign to ``follows``. A
    cube that measures tx well but rz loosely must leave rz's model error whole, so the combined
    rz stays within 3σ of the truth (0): a rank-one term let the cube's tx set rz's share and
    moved rz the wrong way."""
    bias, share = 5e-4, 0.2
    effect = {n: FOLLOWS["incidence_bias"][n] * bias for n in SPIN}
    spin = _estimate({"tx": 0.28 * effect["tx"], "rz": -0.7 * effect["rz"]},
                     {"tx": 1.3e-5, "tz": 2e-5, "ry": 6e-4, "rz": 4.7e-5}, FOLLOWS)
    cube = _estimate({}, {"tx": 6e-6, "tz": 1.3e-5, "ry": 4e-4, "rz": 8.7e-5})
    fused = fuse(spin.with_model_error("incidence_bias", share * bias), cube)
    k = fused.names.index("rz")
    rz, sigma = float(fused.vector[ESTIMATED_NAMES.index("rz")]), fused.sigma["rz"]
    assert abs(rz) < 3 * sigma
    model = math.hypot(4.7e-5, share * effect["rz"])
    assert math.isclose(fused.covariance[k, k], 1 / (1 / model**2 + 1 / 8.7e-5**2), rel_tol=1e-9)
