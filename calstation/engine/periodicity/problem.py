"""The least-squares problem of one outer iteration of the periodicity fine-tuning: the matches
of the two half-turns held fixed, H free. Point-to-local-plane residuals (symmetric) with the
platter residual of the ``platter`` gauge, their closed-form Jacobian, the problem reduced to
n + 1 rows for the inner solve, and the bounds of the parameters."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calstation.engine.frames import PARAMETER_NAMES, FloatArray
from calstation.engine.periodicity.cells import _rotation
from calstation.engine.periodicity.covariance import SIGMA_BLOCK, block_ids
from calstation.engine.settings import PeriodicitySettings

IDX = {name: i for i, name in enumerate(PARAMETER_NAMES)}


@dataclass
class _Matched:
    pa: FloatArray
    ca: FloatArray
    sa: FloatArray
    pb: FloatArray
    cb: FloatArray
    sb: FloatArray
    na: FloatArray
    nb: FloatArray
    wa: FloatArray
    wb: FloatArray
    oa: FloatArray
    ob: FloatArray
    block: NDArray[np.int64]
    """(M,) the spatial block (in D) of each match, for the clustered covariance"""


class _Problem:
    """Residuals of one outer iteration: fixed matches and normals, H free."""

    def __init__(
        self,
        matched: _Matched,
        platter: FloatArray | None,
        platter_weight: float,
        free: list[int],
        x6: FloatArray,
    ) -> None:
        self.m = matched
        self.platter = platter
        self.platter_weight = platter_weight
        self.free = free
        self.base = x6.copy()
        self.swa = np.sqrt(matched.wa)
        self.swb = np.sqrt(matched.wb)
        self._nq: tuple[FloatArray, FloatArray, FloatArray, FloatArray] | None = None

    def row_blocks(self) -> NDArray[np.int64]:
        """(rows,) the spatial block of each residual, in the order of :meth:`residuals`."""
        b = self.m.block
        parts = [b, b]
        if self.platter is not None and self.platter.shape[0]:
            parts.append(block_ids(self.platter, SIGMA_BLOCK) + (int(b.max(initial=-1)) + 1))
        return np.concatenate(parts)

    def full(self, x: FloatArray) -> FloatArray:
        x6 = self.base.copy()
        x6[self.free] = x
        return x6

    def solution(self, x: FloatArray) -> Any:
        """The residuals and the Jacobian at ``x`` in full, as the covariance reads them
        (``fun``, ``jac``, ``x``)."""
        from types import SimpleNamespace

        return SimpleNamespace(x=x, fun=self.residuals(x), jac=self.jacobian(x))

    def _normals_in_q(self) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """Each match's normals turned back by its platter angles: with ``q = Rᵀ(p − t)``,
        ``n·(D(pa) − D(pb)) = ña·qa − ñb·qb``, so the residuals and their derivatives need no
        per-point rotation."""
        if self._nq is None:
            m = self.m

            def back(n: FloatArray, c: FloatArray, s: FloatArray) -> FloatArray:
                return np.column_stack(
                    [n[:, 0], c * n[:, 1] - s * n[:, 2], s * n[:, 1] + c * n[:, 2]]
                )

            self._nq = (
                back(m.na, m.ca, m.sa),
                back(m.na, m.cb, m.sb),
                back(m.nb, m.ca, m.sa),
                back(m.nb, m.cb, m.sb),
            )
        return self._nq

    def residuals(self, x: FloatArray) -> FloatArray:
        x6 = self.full(x)
        m = self.m
        R = _rotation(x6)
        aa, ab, ba, bb = self._normals_in_q()
        ua, ub = m.pa - x6[:3], m.pb - x6[:3]
        # point of B against A's local plane, and point of A against B's local plane
        ra = self.swa * (_rowdot(ua, aa @ R.T) - _rowdot(ub, ab @ R.T) + m.oa)
        rb = self.swb * (_rowdot(ua, ba @ R.T) - _rowdot(ub, bb @ R.T) - m.ob)
        parts = [ra, rb]
        if self.platter is not None and self.platter.shape[0]:
            parts.append(self.platter_weight * ((self.platter - x6[:3]) @ R[:, 0]))
        return np.concatenate(parts)

    def jacobian(self, x: FloatArray) -> FloatArray:
        """(rows, free) derivatives of :meth:`residuals`, in closed form (the rotation's
        derivatives by central differences of the 3×3 matrix, exact to ~1e-12)."""
        x6 = self.full(x)
        m = self.m
        R = _rotation(x6)
        aa, ab, ba, bb = self._normals_in_q()
        ua, ub = m.pa - x6[:3], m.pb - x6[:3]
        platter = self.platter if self.platter is not None else np.zeros((0, 3))
        w = self.platter_weight
        rows = 2 * aa.shape[0] + platter.shape[0]
        J = np.empty((rows, len(self.free)))
        n = aa.shape[0]
        # ∂/∂t: the same three columns for every translation
        ta = -self.swa[:, None] * ((aa - ab) @ R.T)
        tb = -self.swb[:, None] * ((ba - bb) @ R.T)
        for col, i in enumerate(self.free):
            if i < 3:
                J[:n, col] = ta[:, i]
                J[n : 2 * n, col] = tb[:, i]
                J[2 * n :, col] = -w * R[i, 0]
                continue
            dR = _rotation_derivative(x6, i)
            va, vb = ua @ dR, ub @ dR
            J[:n, col] = self.swa * (_rowdot(va, aa) - _rowdot(vb, ab))
            J[n : 2 * n, col] = self.swb * (_rowdot(va, ba) - _rowdot(vb, bb))
            J[2 * n :, col] = w * ((platter - x6[:3]) @ dR[:, 0])
        return J


class _Reduced:
    """The inner solve of one outer iteration on n + 1 rows instead of millions.

    With J₀ = Q·R (thin QR) at the start x₀, ``[Qᵀ·r(x), ‖r₀ − Q·Qᵀ·r₀‖]`` has the full
    problem's gradient direction to first order (the part of r outside the span of J₀ does not
    move with x) and its cost at x₀, so TRF takes the same steps and its tolerances keep their
    meaning, while its linear algebra runs on n + 1 rows. The residuals and the Jacobian are
    still evaluated in full (closed form); the outer loop re-matches and re-linearises anyway.
    """

    def __init__(self, problem: _Problem, x0: FloatArray) -> None:
        self.problem = problem
        J0 = problem.jacobian(x0)
        r0 = problem.residuals(x0)
        self.Q, _ = np.linalg.qr(J0)
        rest = r0 - self.Q @ (self.Q.T @ r0)
        self.rest = float(np.sqrt(rest @ rest))

    def residuals(self, x: FloatArray) -> FloatArray:
        return np.append(self.Q.T @ self.problem.residuals(x), self.rest)

    def jacobian(self, x: FloatArray) -> FloatArray:
        J = self.Q.T @ self.problem.jacobian(x)
        return np.vstack([J, np.zeros((1, J.shape[1]))])


def _rowdot(a: FloatArray, b: FloatArray) -> FloatArray:
    out: FloatArray = np.einsum("ij,ij->i", a, b)
    return out


def _rotation_derivative(x6: FloatArray, i: int, h: float = 1e-6) -> FloatArray:
    """∂R/∂x6[i] (i = 3, 4, 5: rx, ry, rz) by a central difference."""
    up, down = x6.copy(), x6.copy()
    up[i] += h
    down[i] -= h
    out: FloatArray = (_rotation(up) - _rotation(down)) / (2 * h)
    return out


def _free(gauge_ty: bool) -> list[int]:
    names = ["tx", "tz", "ry", "rz"] if gauge_ty else ["tx", "ty", "tz", "ry", "rz"]
    return [IDX[n] for n in names]


def _bounds(
    x6: FloatArray, start6: FloatArray, free: list[int], settings: PeriodicitySettings
) -> tuple[FloatArray, FloatArray]:
    tb = settings.translation_bound
    rb = math.radians(settings.rotation_bound_deg)
    ryb = math.radians(settings.ry_bound_deg)
    lo, hi = [], []
    for i in free:
        if i == IDX["ry"]:
            # never re-centred: ry is nearly unobservable and would walk to a moving bound
            centre, half = start6[i], ryb
            lo.append(centre - half)
            hi.append(centre + half)
            continue
        half = tb if i < 3 else rb
        lo.append(x6[i] - half)
        hi.append(x6[i] + half)
    lo_a, hi_a = np.array(lo), np.array(hi)
    x = x6[free]
    eps = 1e-9
    return np.minimum(lo_a, x - eps), np.maximum(hi_a, x + eps)


def _platter_samples(
    p_static: FloatArray, x6: FloatArray, tolerance: float, radius: float
) -> FloatArray:
    """Static returns that lie on the platter top under H (|x_P| ≤ tolerance, inside radius)."""
    if p_static.shape[0] == 0:
        return p_static
    q = (p_static - x6[:3]) @ _rotation(x6)
    r = np.hypot(q[:, 1], q[:, 2])
    keep = (np.abs(q[:, 0]) <= tolerance) & (r <= radius)
    return p_static[keep]
