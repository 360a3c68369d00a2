"""The uncertainty of a least-squares estimate: parameter covariance and σ, independent or
cluster-robust over spatial blocks, and the constant factor on the periodicity σ for what the
block sandwich does not see.

Used by the periodicity fine-tuning, and by the shape strategy and the cube check for theirs.
"""

from __future__ import annotations

import math
from typing import Protocol, TypedDict

import numpy as np
from numpy.typing import NDArray

from calstation.engine.frames import PARAMETER_NAMES, FloatArray
from calstation.engine.periodicity.cells import _groups
from calstation.engine.rangemodel import ESTIMATED_NAMES

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


SIGMA_SCALE = 1.3
"""Factor on the last stage's block-sandwich σ for what the sandwich does not see (see
:func:`noise_inflation`)."""


def noise_inflation(noise: float) -> float:
    """Factor (≥ 1) on the block-sandwich σ of the last stage: :data:`SIGMA_SCALE` for a noisy
    scan, 1 for a noise-free or unknown one.

    The residuals along the rays (target and platter) and the one-sided matching leave no bias
    that grows with the noise (docs/algorithms.md), so the factor does not grow with it, and
    σ falls as turns are added. What the sandwich still misses (the matching and the plane
    fits move with the noise, which its fixed-correspondence Jacobian does not see) was measured
    on the simulator: the RMS of error/σ was 1.29 (ry), 0.89 (tx), 1.35 (tz) and 1.28 (rz) over
    144 runs at 1 and 2 mm, 1–8 turns, five scenes (centred and off-centre targets, background
    on and off, 180 and 1000 lines/s), and did not change with the turns.
    """
    if not math.isfinite(noise) or noise <= 0:
        return 1.0
    return SIGMA_SCALE


MODEL_FLOOR_DEG = {"ry": 0.01, "rz": 0.002}
"""1σ (degrees) of the periodicity's model error, added in quadrature to the reported σ of
ry and rz: what remains once the noise is gone. On noise-free simulated scans the last stage
left +0.013 to +0.027° of ry on a centred target and 0.0006–0.004° of rz; with σ falling with
the turns, a 4-turn scan at 1000 lines/s reported σ_rz 0.001° for an error of 0.0037°."""


class LeastSquaresSolution(Protocol):
    """What the covariance reads of a least-squares solution (``scipy.optimize.least_squares``'s
    result, or a problem's own :class:`~calstation.engine.periodicity.problem.Solution`): the
    residuals ``fun`` (m,) and their Jacobian ``jac`` (m, n)."""

    @property
    def fun(self) -> FloatArray:
        """The residuals (m,)."""
        ...

    @property
    def jac(self) -> FloatArray:
        """Their Jacobian (m, n)."""
        ...


class CovarianceRecord(TypedDict):
    """A covariance as stored with a calibration: the parameter names and the matrix (SI)."""

    parameters: list[str]
    matrix: list[list[float]]


def model_floor(free: list[int]) -> FloatArray:
    """The (n, n) diagonal covariance of :data:`MODEL_FLOOR_DEG` over the parameters ``free``."""
    floor = [math.radians(MODEL_FLOOR_DEG.get(ESTIMATED_NAMES[i], 0.0)) ** 2 for i in free]
    out: FloatArray = np.diag(floor)
    return out


def parameter_covariance(
    res: LeastSquaresSolution, free: list[int], blocks: NDArray[np.int64] | None = None
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
    res: LeastSquaresSolution, free: list[int], blocks: NDArray[np.int64] | None = None
) -> dict[str, float]:
    """1σ per parameter (metres / radians, keyed by ``PARAMETER_NAMES``, and the range terms
    among ``free``) from :func:`parameter_covariance`; NaN for parameters held fixed, and for
    all when the covariance cannot be computed."""
    return sigma_from_covariance(parameter_covariance(res, free, blocks), free)


def covariance_record(cov: FloatArray | None, free: list[int]) -> CovarianceRecord | None:
    """The covariance as stored with a calibration: parameter names and the matrix (SI)."""
    if cov is None:
        return None
    return {"parameters": [ESTIMATED_NAMES[i] for i in free], "matrix": cov.tolist()}


def sigma_from_covariance(cov: FloatArray | None, free: list[int]) -> dict[str, float]:
    """1σ per parameter name from an (n, n) covariance of the parameters ``free`` (indices of
    :data:`~calstation.engine.rangemodel.ESTIMATED_NAMES`): every one of H's (NaN when held),
    and the range terms that are free."""
    out = {n: math.nan for n in PARAMETER_NAMES}
    for i in free:
        out[ESTIMATED_NAMES[i]] = math.nan
    if cov is None:
        return out
    for k, i in enumerate(free):
        out[ESTIMATED_NAMES[i]] = float(math.sqrt(max(cov[k, k], 0.0)))
    return out
