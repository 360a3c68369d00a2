"""Soft-L1 least squares by Gauss–Newton steps on the normal equations, for fits of many
residuals and few parameters (calstation; docs/performance.md).

SciPy's ``least_squares(method="trf")`` solves each step's trust-region problem from the
singular value decomposition of the (m, n) Jacobian. With m of 150 000 residuals and n of a
dozen parameters, that decomposition cost about as much as the Jacobian itself (31 ms against
40 ms on the known-size cube fit's last round). Near its minimum, which is where the fits
this module serves start, TRF's trust region does not bind: each step is the Gauss–Newton step
of the loss-scaled problem. :func:`soft_l1_fit` takes the same step from the (n, n) normal
equations, accepts it by the same tests (``ftol``, ``xtol``, ``gtol`` as TRF's, in its scaled
variables). A step that does not lower the cost is halved, up to :data:`HALVINGS` times, and
the fit goes on by its own steps from the first that does (from the L-target's start, the shape
strategy's first step overshoots: TRF starting again from there took 0.07–0.12 s); when none
does, the fit is handed to TRF from where it stands: from a far start the trust region matters.
A shortened step never ends the fit: the tests that end it are taken on whole steps.

The result is a :class:`scipy.optimize.OptimizeResult` as TRF's: ``x``; ``fun`` the residuals;
``jac`` the Jacobian scaled by the loss (each row by √(ρ′ + 2zρ″), so that JᵀJ is the
Gauss–Newton Hessian, as TRF returns it); ``cost``; ``nfev``, ``njev``, ``status``,
``message``.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from scipy.optimize import OptimizeResult, least_squares

from calstation.engine.frames import FloatArray

HALVINGS = 3
"""Times a step that does not lower the cost is halved before TRF takes the fit over."""
TOL = 1e-8
"""``ftol``, ``xtol`` and ``gtol``: TRF's defaults."""
EPS = float(np.finfo(np.float64).eps)

_MESSAGES = {
    1: "`gtol` termination condition is satisfied.",
    2: "`ftol` termination condition is satisfied.",
    3: "`xtol` termination condition is satisfied.",
    4: "Both `ftol` and `xtol` termination conditions are satisfied.",
    0: "The maximum number of function evaluations is exceeded.",
}


def _scaled(
    f: FloatArray, J: FloatArray, f_scale: float
) -> tuple[float, FloatArray, FloatArray]:
    """The soft-L1 cost of residuals ``f`` and the Jacobian and residuals scaled for it
    (scipy's ``scale_for_robust_loss_function``: J·√w, f·ρ′/√w, w = ρ′ + 2zρ″)."""
    z = (f / f_scale) ** 2
    t = 1.0 + z
    cost = float(np.sum(t**0.5 - 1.0)) * f_scale**2
    rho1 = t**-0.5
    weight = _weight(z, t, rho1)
    return cost, J * weight[:, None], f * (rho1 / weight)


def gauss_newton_weight(z: FloatArray) -> FloatArray:
    """√w of soft-L1's Gauss–Newton weights w = ρ′(z) + 2z·ρ″(z) at z = (r/f_scale)², floored
    at machine ε as scipy's ``scale_for_robust_loss_function`` floors them: the weights a
    soft-L1 fit's rows carry (in ``OptimizeResult.jac``, each row scaled by √w)."""
    t = 1.0 + z
    return _weight(z, t, t**-0.5)


def _weight(z: FloatArray, t: FloatArray, rho1: FloatArray) -> FloatArray:
    """:func:`gauss_newton_weight` from z, t = 1 + z and ρ′ = t^-½ already computed."""
    out: FloatArray = np.maximum(rho1 - z * t**-1.5, EPS) ** 0.5
    return out


def _cost(f: FloatArray, f_scale: float) -> float:
    return float(np.sum((1.0 + (f / f_scale) ** 2) ** 0.5 - 1.0)) * f_scale**2


def soft_l1_fit(
    fun: Callable[[FloatArray], FloatArray],
    jac: Callable[[FloatArray], FloatArray],
    x0: FloatArray,
    *,
    f_scale: float,
    x_scale: FloatArray,
    max_nfev: int,
) -> OptimizeResult:
    """``least_squares(fun, x0, jac=jac, method="trf", loss="soft_l1", f_scale=f_scale,
    x_scale=x_scale, max_nfev=max_nfev)``, by Gauss–Newton steps on the normal equations while
    each, or its half, quarter or eighth, lowers the cost, by TRF from there when none does
    (see the module)."""
    x = np.asarray(x0, dtype=np.float64).copy()
    d = np.asarray(x_scale, dtype=np.float64)
    f = np.asarray(fun(x), dtype=np.float64)
    J = np.asarray(jac(x), dtype=np.float64)
    nfev = njev = 1
    cost, Js, fs = _scaled(f, J, f_scale)
    status = None
    while True:
        g = Js.T @ fs
        if float(np.max(np.abs(g))) < TOL:
            status = 1
            break
        if nfev >= max_nfev:
            status = 0
            break
        g_h = g * d
        Jh = Js * d
        A = Jh.T @ Jh
        try:
            step_h = -np.linalg.solve(A, g_h)
        except np.linalg.LinAlgError:
            return _trf(fun, jac, x, f_scale, d, max_nfev, nfev, njev)
        whole = True
        for _ in range(HALVINGS + 1):
            x_new = x + d * step_h
            f_new = np.asarray(fun(x_new), dtype=np.float64)
            nfev += 1
            cost_new = _cost(f_new, f_scale) if np.all(np.isfinite(f_new)) else math.inf
            if cost_new < cost or nfev >= max_nfev:
                break
            step_h, whole = step_h * 0.5, False
        reduction = cost - cost_new
        if reduction <= 0:
            return _trf(fun, jac, x, f_scale, d, max_nfev, nfev, njev)
        predicted = -float(g_h @ step_h + 0.5 * step_h @ A @ step_h)
        ratio = reduction / predicted if predicted > 0 else 0.0
        # a shortened step lowers the cost by less than a whole one would: the fit goes on
        ftol_met = whole and reduction < TOL * cost and ratio > 0.25
        xtol_met = whole and (float(np.linalg.norm(d * step_h))
                                     < TOL * (TOL + float(np.linalg.norm(x))))
        x, f = x_new, f_new
        J = np.asarray(jac(x), dtype=np.float64)
        njev += 1
        cost, Js, fs = _scaled(f, J, f_scale)
        if ftol_met or xtol_met:
            status = 4 if ftol_met and xtol_met else 2 if ftol_met else 3
            break
    return OptimizeResult(
        x=x, fun=f, jac=Js, cost=cost, grad=Js.T @ fs, nfev=nfev, njev=njev, status=status,
        message=_MESSAGES[status], success=status > 0,
    )


def _trf(
    fun: Callable[[FloatArray], FloatArray], jac: Callable[[FloatArray], FloatArray],
    x: FloatArray, f_scale: float, d: FloatArray, max_nfev: int, nfev: int, njev: int,
) -> OptimizeResult:
    """TRF from ``x``, with the evaluations left; its counts include those made before."""
    res = least_squares(fun, x, jac=jac, method="trf", loss="soft_l1", f_scale=f_scale,
                        x_scale=d, max_nfev=max(max_nfev - nfev, 1))
    res.nfev += nfev
    res.njev = int(res.njev or 0) + njev
    return res
