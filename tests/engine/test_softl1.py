"""The soft-L1 fit by Gauss–Newton steps on the normal equations (calstation.engine.softl1):
the minimum, the scaled Jacobian and the evaluations of SciPy's TRF, whose steps it takes."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from scipy.optimize import least_squares

from calstation.engine.softl1 import HALVINGS, gauss_newton_weight, soft_l1_fit


class Circles:
    """Range-like residuals of many points against a few circles (centre, radius each): a
    nonlinear problem of many residuals and few parameters, with 3 % of the points strays
    that the soft-L1 loss must discount."""

    def __init__(self, seed: int) -> None:
        rng = np.random.default_rng(seed)
        self.truth = np.array([0.1, -0.2, 0.5, 0.7, 0.3, 0.25])
        k = rng.integers(0, 2, 20_000)
        angle = rng.uniform(0.0, 2 * np.pi, k.size)
        cx, cy, r = (self.truth.reshape(2, 3)[k, j] for j in range(3))
        noise = rng.normal(0.0, 1e-3, k.size)
        noise[rng.random(k.size) < 0.03] += rng.uniform(0.01, 0.05, k.size)[:1]
        self.k, self.x = k, cx + (r + noise) * np.cos(angle)
        self.y = cy + (r + noise) * np.sin(angle)
        self.evaluations = 0

    def __call__(self, p: np.ndarray) -> np.ndarray:
        self.evaluations += 1
        c = p.reshape(2, 3)[self.k]
        out: np.ndarray = np.hypot(self.x - c[:, 0], self.y - c[:, 1]) - c[:, 2]
        return out

    def jac(self, p: np.ndarray) -> np.ndarray:
        c = p.reshape(2, 3)[self.k]
        dx, dy = self.x - c[:, 0], self.y - c[:, 1]
        d = np.hypot(dx, dy)
        out = np.zeros((self.k.size, 6))
        rows = np.arange(self.k.size)
        out[rows, 3 * self.k] = -dx / d
        out[rows, 3 * self.k + 1] = -dy / d
        out[rows, 3 * self.k + 2] = -1.0
        return out


def _sigma(trf: Any) -> np.ndarray:
    """1σ of each parameter of TRF's fit, from its loss-scaled Jacobian."""
    out: np.ndarray = np.sqrt(np.diag(np.linalg.inv(trf.jac.T @ trf.jac)) * np.mean(trf.fun**2))
    return out


def _both(problem: Circles, x0: np.ndarray) -> tuple[Any, Any]:
    options: dict[str, Any] = {"f_scale": 3e-3, "x_scale": np.full(6, 1e-3), "max_nfev": 100}
    trf = least_squares(problem, x0, jac=problem.jac, method="trf", loss="soft_l1", **options)
    return trf, soft_l1_fit(problem, problem.jac, x0, **options)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_from_near_its_minimum_the_fit_is_trfs(seed: int) -> None:
    """From a start a few millimetres off, the fit's minimum and its loss-scaled Jacobian (what
    the covariances are computed from) are TRF's, with at most one more Jacobian and the
    evaluations of a halved step beyond TRF's."""
    problem = Circles(seed)
    x0 = problem.truth + np.random.default_rng(seed).normal(0.0, 3e-3, 6)
    trf, fit = _both(problem, x0)
    sigma = _sigma(trf)
    assert np.max(np.abs(fit.x - trf.x) / sigma) < 1e-6
    np.testing.assert_allclose(fit.jac, trf.jac, rtol=0, atol=1e-9 * np.abs(trf.jac).max())
    np.testing.assert_allclose(fit.fun, trf.fun, rtol=0, atol=1e-9)
    assert fit.cost == pytest.approx(trf.cost, rel=1e-9)
    assert fit.njev <= trf.njev + 1 and fit.nfev <= trf.nfev + HALVINGS + 1
    assert fit.success
    # the strays are discounted, not fitted: the radii within a few σ of the truth
    assert np.max(np.abs(fit.x - problem.truth) / sigma) < 5


def test_a_step_that_overshoots_is_halved_and_ends_where_trf_does(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """From a start 1 cm off, a Gauss–Newton step raises the cost; halved, it lowers it, and
    the fit goes on by its own steps (TRF made to raise if called) to TRF's minimum."""
    from calstation.engine import softl1

    def no_trf(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("handed to TRF")

    # the fit's own TRF raises; the reference's (this module's) runs
    monkeypatch.setattr(softl1, "least_squares", no_trf)
    problem = Circles(0)
    trf, fit = _both(problem, problem.truth + np.random.default_rng(10).normal(0.0, 0.01, 6))
    assert fit.success and fit.nfev > fit.njev + 1  # some step was shortened
    sigma = _sigma(trf)
    assert np.max(np.abs(fit.x - trf.x) / sigma) < 1e-6


def test_a_step_that_halving_cannot_save_hands_the_fit_to_trf() -> None:
    """From a start far off (the circles' centres 5 cm out), where a Gauss–Newton step
    raises the cost however it is halved, the fit goes on by TRF from where it stands and ends
    where TRF does."""
    problem = Circles(4)
    x0 = problem.truth + np.array([0.05, -0.05, -0.2, -0.05, 0.05, 0.2])
    trf, fit = _both(problem, x0)
    assert trf.success and fit.success
    sigma = _sigma(trf)
    assert np.max(np.abs(fit.x - trf.x) / sigma) < 1e-3
    assert fit.nfev <= 100


def test_the_gauss_newton_weights_are_those_trf_scales_its_rows_by() -> None:
    """The weights a soft-L1 fit's rows carry (the cube fit's responses read them back out of
    its Jacobian): TRF's own, row by row, at every size of residual."""
    f_scale = 2e-3
    r = np.array([0.0, 1e-4, -2e-3, 5e-3, -0.05, 1.0, 1e3])
    fit = least_squares(lambda x: r * x[0], np.array([1.0]), lambda x: r[:, None],
                        loss="soft_l1", f_scale=f_scale,
                        max_nfev=1)
    # at x = 1 the unscaled Jacobian is r itself: TRF's rows are r·√w
    got = gauss_newton_weight((fit.fun / f_scale) ** 2)
    assert np.allclose(fit.jac[:, 0], fit.fun * got, rtol=1e-12, atol=0.0)
    assert got[0] == 1.0 and np.all(np.diff(got[1:4]) < 0) and got[-1] > 0.0
