"""The uncertainty of a least-squares estimate: parameter covariance and σ, independent or
cluster-robust over spatial blocks, and the inflation of σ for the bias range noise leaves.

Used by the periodicity fine-tuning, and by the shape strategy and the cube check for theirs.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calstation.engine.frames import PARAMETER_NAMES, FloatArray
from calstation.engine.periodicity.cells import _groups

SIGMA_BLOCK = 0.02
"""Edge (m) of the spatial blocks whose residuals are taken as correlated in the covariance."""


def block_ids(points: FloatArray, size: float) -> NDArray[np.int64]:
    """(N,) a dense block index for (N, 3) points on a grid of ``size`` m."""
    if points.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    cells = np.floor(points / size).astype(np.int64)
    cells -= cells.min(axis=0)
    span = cells.max(axis=0) + 1
    key = (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]
    return _groups(key)[0]


NOISE_BIAS_GAIN = 0.5
"""Empirical gain of the noise term in the reported σ (see :func:`noise_inflation`)."""


def noise_inflation(noise: float) -> float:
    """Factor (≥ 1) on the Jacobian σ for the bias that range noise leaves in the estimate.

    Noise along each ray moves a return's height and its distance to the matched plane
    together, so the heights that carry ry (and tz with it) are correlated with the residuals:
    an errors-in-variables bias that grows with σ² relative to the information, while the
    Jacobian σ grows with σ. On the simulated station (docs/algorithms.md: noise 0.5–2 mm,
    background on and off, centred and off-centre targets, 180 and 1000 lines/s) the errors
    stayed within 3 of σ·√(1 + (g·(σ_noise / 1 mm)²)²) with g = :data:`NOISE_BIAS_GAIN`.
    1 for an unknown noise.
    """
    if not math.isfinite(noise) or noise <= 0:
        return 1.0
    return math.sqrt(1.0 + (NOISE_BIAS_GAIN * (noise / 0.001) ** 2) ** 2)


def parameter_covariance(
    res: Any, free: list[int], blocks: NDArray[np.int64] | None = None
) -> FloatArray | None:
    """(n, n) covariance of the n parameters with indices ``free`` at the solution of
    ``scipy.optimize.least_squares`` (``res.jac`` (m, n), ``res.fun`` (m,)); None when m ≤ n
    or JᵀJ is singular.

    Without ``blocks``: σ²·(JᵀJ)⁻¹, which assumes independent residuals. With ``blocks`` (m,)
    (the spatial block of each residual): each parameter's variance is the larger of that and
    the cluster-robust sandwich (JᵀJ)⁻¹·(Σ_g J_gᵀ r_g r_gᵀ J_g)·(JᵀJ)⁻¹ · G/(G − 1), whose
    blocks' residuals may co-vary freely (neighbouring residuals share normals, plane fits and
    cell averages); the correlations are those of σ²·(JᵀJ)⁻¹, so the matrix stays positive
    semi-definite.
    """
    J = np.asarray(res.jac, dtype=np.float64)
    r = np.asarray(res.fun, dtype=np.float64)
    m, n = J.shape
    if m <= n:
        return None
    try:
        inv = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return None
    cov: FloatArray = float(np.sum(r**2)) / (m - n) * inv
    if blocks is not None:
        g = int(blocks.max()) + 1
        if g <= n:
            return None
        scores = np.column_stack(
            [np.bincount(blocks, weights=J[:, k] * r, minlength=g) for k in range(n)]
        )
        sandwich = inv @ (scores.T @ scores) @ inv * (g / (g - 1))
        iid = np.sqrt(np.maximum(np.diag(cov), 1e-300))
        scale = np.sqrt(np.maximum(np.diag(cov), np.diag(sandwich))) / iid
        cov = cov * np.outer(scale, scale)
    return cov


def parameter_sigma(
    res: Any, free: list[int], blocks: NDArray[np.int64] | None = None
) -> dict[str, float]:
    """1σ per parameter (metres / radians, keyed by ``PARAMETER_NAMES``) from
    :func:`parameter_covariance`; NaN for parameters held fixed, and for all when the
    covariance cannot be computed."""
    return sigma_from_covariance(parameter_covariance(res, free, blocks), free)


def covariance_record(cov: FloatArray | None, free: list[int]) -> dict[str, Any] | None:
    """The covariance as stored with a calibration: parameter names and the matrix (SI)."""
    if cov is None:
        return None
    return {"parameters": [PARAMETER_NAMES[i] for i in free], "matrix": cov.tolist()}


def sigma_from_covariance(cov: FloatArray | None, free: list[int]) -> dict[str, float]:
    """1σ per parameter name from an (n, n) covariance of the parameters ``free``."""
    out = {n: math.nan for n in PARAMETER_NAMES}
    if cov is None:
        return out
    for k, i in enumerate(free):
        out[PARAMETER_NAMES[i]] = float(math.sqrt(max(cov[k, k], 0.0)))
    return out
