"""Two estimates of the calibration combined in information form: the spin target's and the QA
cube's, each with its covariance over the parameters it estimated.

The spin scan and the cube scan see different things. The spin target's periodicity fixes the
axis (tx, tz, rz) and, with the platter, the range offset only weakly (about b/(2ρ) of tilt per
metre of offset, against the platter's own tilt); it cannot see a range scale error at all (a
world scaled by 1 + ε turns alike, with the translation scaled too), and reads an incidence bias
as an axis offset (its facets are seen at about 25° from one side and 65° from the other): it
holds both and reports how it would follow them (``diagnostics["follows"]``). The cube's known
edge and height and its square faces, seen at every angle as it turns, fix the offset, the scale
error and the incidence bias, and see ry well. Each estimate is a Gaussian
over its own parameters; their product is the combined estimate, exact for the linear part and
the same as a joint fit of both scans once both are near the solution (they are: the cube's fit
starts from the spin target's result).

The cube's bias bound (what its edge tolerance moves, fully correlated across the parameters) is
part of its covariance here, as the rank-one term it is, so the combination leans on the cube
only as far as its tolerance allows. The spin target's incidence correction is a model: what it
may miss is an independent variance on each parameter (:meth:`Estimate.with_model_error`).

Both fixtures turn on one encoder, whose angle error neither fit models: it moves both
estimates, each its own way (:mod:`calstation.engine.encoder`). Its four coefficients are
estimated beside H, each held by the encoder's stated accuracy as a prior
(:meth:`Estimate.with_encoder`): what the fixtures' difference says of them corrects both, and
the rest stays in the combined σ.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, TypedDict

import numpy as np
from scipy.special import chdtrc

from calstation.engine.frames import PARAMETER_NAMES, Extrinsics, FloatArray
from calstation.engine.rangemodel import ESTIMATED_NAMES, RangeModel

if TYPE_CHECKING:
    from calstation.engine.periodicity.covariance import CovarianceRecord

CONSISTENCY_P = 1e-3
"""Two estimates whose difference is less likely than this under their combined covariance
are not combined: one of them is wrong (a misplaced fixture, an error neither models)."""


@dataclass(frozen=True)
class Estimate:
    """An estimate of some of :data:`~calstation.engine.rangemodel.ESTIMATED_NAMES`.

    ``vector`` (8,) every parameter's value (held ones too); ``names`` and ``covariance`` the
    estimated ones and their (n, n) covariance (SI). ``follows`` (per name of ``names``): how
    the estimate moves per unit of a parameter it held (``{"range_scale": {"tx": …}}``).
    """

    vector: FloatArray
    names: tuple[str, ...]
    covariance: FloatArray
    follows: Mapping[str, Mapping[str, float]]
    consider: FloatArray | None = None
    """(n, m) how the estimate moves per 1σ of each of m parameters that neither estimate
    models and both share (the encoder's angle error, :meth:`with_encoder`); None: m = 0"""

    @classmethod
    def of(cls, H: Extrinsics, model: RangeModel, record: CovarianceRecord,
           follows: Mapping[str, Mapping[str, float]] | None = None) -> Estimate:
        """From H, the range model and a stored covariance record (``parameters``,
        ``matrix``)."""
        return cls(
            np.concatenate([H.as_vector(), model.as_vector()]),
            tuple(str(n) for n in record["parameters"]),
            np.asarray(record["matrix"], dtype=np.float64),
            dict(follows or {}),
        )

    def with_model_error(self, held: str, size: float) -> Estimate:
        """The estimate with the error of how it corrects for a parameter it ``held`` added to
        its covariance: for each parameter, its ``follows`` coefficient times ``size`` (in the
        held parameter's unit) as an independent variance. Independent, not the rank-one term
        along ``follows``: what a correction whose shape is only a model misses does not move
        the estimate along the direction the whole parameter would (on the simulator the spin
        target's tx kept about 28 % of an incidence bias's effect and its rz about 70 %, of
        opposite sign to ``follows``), and a rank-one term would let another fixture's tx tell
        the combination how far rz is off."""
        direction = self.follows.get(held)
        if not direction or size == 0.0:
            return self
        v = np.array([float(direction.get(n, 0.0)) * size for n in self.names])
        return replace(self, covariance=self.covariance + np.diag(v * v))

    def with_encoder(self, directions: Mapping[str, Mapping[str, float]] | None,
                     sigma: float) -> Estimate:
        """The estimate with the encoder's angle error as the shared parameters it is
        (:mod:`calstation.engine.encoder`): ``directions`` how it moves per radian of each
        coefficient (:data:`~calstation.engine.encoder.HARMONICS`; missing: it does not), each
        coefficient of 1σ ``sigma`` (rad). Itself when ``sigma`` is zero."""
        from calstation.engine.encoder import columns

        if sigma <= 0.0:
            return self
        return replace(self, consider=columns(directions, self.names, sigma))

    def shared(self, m: int) -> FloatArray:
        """(n, m) :attr:`consider`, zeros when the estimate has none."""
        if self.consider is None or self.consider.shape[1] == 0:
            return np.zeros((len(self.names), m))
        return self.consider


class Disagreement(TypedDict):
    """How far apart two estimates are on the parameters both estimated: the χ² of their
    difference, its degrees of freedom and p-value, and each parameter's difference in σ."""

    chi2: float
    dof: int
    p: float
    sigmas: dict[str, float]


@dataclass(frozen=True)
class Fused:
    """The combined estimate: H, the range model, their covariance (``names``), and how far
    apart the two were (``disagreement``: the χ² of their difference, ``dof``, its p-value,
    and the parameters that differ most, in σ)."""

    H: Extrinsics
    range_model: RangeModel
    names: tuple[str, ...]
    covariance: FloatArray
    disagreement: Disagreement

    @property
    def vector(self) -> FloatArray:
        """(8,) H's parameters then the range terms (:data:`~calstation.engine.rangemodel.
        ESTIMATED_NAMES`)."""
        out: FloatArray = np.concatenate([self.H.as_vector(), self.range_model.as_vector()])
        return out

    @property
    def sigma(self) -> dict[str, float]:
        """1σ per estimated parameter (SI)."""
        return {n: math.sqrt(max(float(self.covariance[k, k]), 0.0))
                for k, n in enumerate(self.names)}

    def record(self) -> CovarianceRecord:
        """The covariance as stored with a calibration."""
        return {"parameters": list(self.names), "matrix": self.covariance.tolist()}


def fuse(first: Estimate, second: Estimate) -> Fused:
    """The product of the two estimates' Gaussians over the union of their parameters (in the
    order of :data:`ESTIMATED_NAMES`). A parameter that ``first`` held but ``second`` estimates
    moves ``first``'s constraint along its ``follows`` direction (the range scale error the spin
    scan cannot see). Parameters neither estimated keep ``first``'s value."""
    names = tuple(n for n in ESTIMATED_NAMES if n in first.names or n in second.names)
    size, m = len(names), _shared_count(first, second)
    # the shared parameters (in σ) are estimated beside the others, each held by its prior
    info = np.zeros((size + m, size + m))
    info[size:, size:] = np.eye(m)
    eta = np.zeros(size + m)
    constraints = []
    for est in (first, second):
        A, z = _constraint(est, names)
        A = np.hstack([A, est.shared(m)])
        inv = np.asarray(np.linalg.inv(0.5 * (est.covariance + est.covariance.T)),
                         dtype=np.float64)
        info += A.T @ inv @ A
        eta += A.T @ inv @ z
        constraints.append((A, z, inv))
    full = np.linalg.inv(info)
    solution = full @ eta
    y = solution[:size]
    cov: FloatArray = np.asarray(full[:size, :size], dtype=np.float64)
    vector = first.vector.copy()
    for k, n in enumerate(names):
        vector[ESTIMATED_NAMES.index(n)] = y[k]
    H = Extrinsics.from_vector(vector[: len(PARAMETER_NAMES)]).with_(rx=0.0)
    return Fused(H, RangeModel.from_vector(vector), names, cov,
                 _disagreement(first, second, constraints, solution, size))


def kalman_update(C: FloatArray, i: int, variance: float) -> tuple[FloatArray, FloatArray]:
    """The Kalman update of the covariance ``C`` by one measurement of its parameter ``i`` with
    ``variance``: (the gain, how far each parameter moves per unit of the measurement's
    difference from the estimate; the covariance after it)."""
    gain: FloatArray = C[:, i] / (C[i, i] + variance)
    after: FloatArray = C - np.outer(gain, C[i, :])
    return gain, after


def _shared_count(first: Estimate, second: Estimate) -> int:
    """How many shared parameters the two estimates carry (:attr:`Estimate.consider`)."""
    return max((e.consider.shape[1] for e in (first, second) if e.consider is not None),
               default=0)


def _constraint(est: Estimate, names: Sequence[str]) -> tuple[FloatArray, FloatArray]:
    """The linear constraint ``A·y = z`` (with ``est``'s covariance) that ``est`` puts on the
    combined parameters ``y`` (``names``): its own parameters, moved along ``follows`` for the
    ones it held."""
    A = np.zeros((len(est.names), len(names)))
    z = np.array([est.vector[ESTIMATED_NAMES.index(n)] for n in est.names])
    for row, n in enumerate(est.names):
        A[row, names.index(n)] = 1.0
    for held, direction in est.follows.items():
        if held not in names or held in est.names:
            continue
        col = names.index(held)
        at = float(est.vector[ESTIMATED_NAMES.index(held)])
        for row, n in enumerate(est.names):
            d = float(direction.get(n, 0.0))
            # y_n − d·(y_held − at) = x_n: the estimate follows the held parameter
            A[row, col] -= d
            z[row] -= d * at
    return A, z


def _disagreement(
    first: Estimate, second: Estimate,
    constraints: list[tuple[FloatArray, FloatArray, FloatArray]], solution: FloatArray,
    size: int,
) -> Disagreement:
    """How far apart the two estimates are: the χ² of the combination at its solution (each
    estimate's constraints ``(A, z, C⁻¹)`` against ``solution``, and the shared parameters'
    priors), on as many degrees of freedom as constraints beyond the ``size`` parameters; and,
    per parameter both estimated, the difference of their residuals there in σ of the
    difference. Not the difference of the two estimates at the second's values of what the
    first held: those values are uncertain too (the cube's ty to 0.07 mm, which the spin
    target's tx follows one to one), and the combination sets them between the two."""
    common = [n for n in first.names if n in second.names]
    dof = len(first.names) + len(second.names) - size
    if not common or dof <= 0:
        return Disagreement(chi2=0.0, dof=0, p=1.0, sigmas={})
    residuals = [A @ solution - z for A, z, _ in constraints]
    value = sum(float(r @ inv @ r) for r, (_, _, inv) in zip(residuals, constraints,
                                                               strict=True))
    value += float(solution[size:] @ solution[size:])
    sigmas = {}
    for n in common:
        i1, i2 = first.names.index(n), second.names.index(n)
        spread = first.covariance[i1, i1] + second.covariance[i2, i2]
        sigmas[n] = float((residuals[1][i2] - residuals[0][i1]) / math.sqrt(max(spread, 1e-300)))
    # the χ² survival function (scipy.stats.chi2.sf computes exactly this), without
    # importing scipy.stats: ~0.4 s at the cube step, while the operator waits
    return Disagreement(chi2=value, dof=dof, p=float(chdtrc(dof, value)), sigmas=sigmas)


def consistent(fused: Fused) -> bool:
    """Whether the two estimates agreed well enough to be combined (:data:`CONSISTENCY_P`)."""
    return bool(fused.disagreement["p"] >= CONSISTENCY_P)
