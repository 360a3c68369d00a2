"""The least-squares problem of one outer iteration of the periodicity fine-tuning: the matches
of the two half-turns held fixed, H free. Point-to-local-plane residuals (symmetric in the coarse
stages; one-sided and measured along the point's ray in the last) with the platter residual of
the ``platter`` gauge (each static return's range error against the plane x_P = 0), their
closed-form Jacobian, the problem reduced to n + 1 rows for the inner solve, and the bounds of
the parameters.

The estimated vector holds H's six parameters and the lidar's range model (the range offset b
and scale error k, :mod:`calstation.engine.rangemodel`): every return is moved along its ray to
its corrected range before it is reconstructed, so b and k are free parameters like H's when the
recipe's ``calibration.range_model`` estimates them (held at their start otherwise)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from calstation.engine.frames import FloatArray, rotation_derivative, rowdot
from calstation.engine.kept import Kept
from calstation.engine.periodicity.cells import _rotation
from calstation.engine.periodicity.covariance import SIGMA_BLOCK, block_ids
from calstation.engine.rangemodel import (
    ESTIMATED_NAMES,
    INCIDENCE,
    OFFSET,
    SCALE,
    correct_vector,
    incidence_shape,
)
from calstation.engine.settings import PeriodicitySettings

IDX = {name: i for i, name in enumerate(ESTIMATED_NAMES)}

RANGE_OFFSET_BOUND = 0.05
"""Half-width (m) of the range offset's bounds around its start: well beyond the ±30 mm
accuracy of the lidars' datasheets."""
RANGE_SCALE_BOUND = 0.01
"""Half-width of the range scale error's bounds around its start (1 %)."""
INCIDENCE_BOUND = 0.02
"""Half-width (m) of the incidence bias's bounds around its start (its value at 60°)."""

PLATTER_NOISE_FLOOR = 1e-4
"""Least range noise (m) the platter's weight assumes (:meth:`_Problem._platter_scale`): a
noise-free (simulated) scan would give its platter unbounded weight and an unbounded σ."""

GRAZING_PLATTER = 0.05
"""Least |cosine| of a platter return's ray with the axis its range error is divided by."""
GRAZING_TARGET = 0.2
"""Least |cosine| of a target cell's ray with its matched plane its range error is divided by."""



@dataclass(frozen=True)
class Solution:
    """A solution ``x`` with its residuals ``fun`` and their Jacobian ``jac`` in full."""

    x: FloatArray
    fun: FloatArray
    jac: FloatArray

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
    one_sided: bool = False
    """only the point of B against A's plane counts (``nb``, ``wb``, ``ob`` unused): the
    one-sided matching puts each plane's cell in A and the point matched to it in B"""


class _Problem:
    """Residuals of one outer iteration: fixed matches and normals, H free.

    ``noise``: the scan's range noise σ (m; NaN when unknown), which weights the platter's
    residuals against the target's (:meth:`_platter_scale`)."""

    def __init__(
        self,
        matched: _Matched,
        platter: FloatArray | None,
        platter_weight: float,
        free: list[int],
        x6: FloatArray,
        noise: float = math.nan,
        platter_level_free: bool = False,
    ) -> None:
        self.m = matched
        self.platter = platter
        self.platter_level_free = platter_level_free
        """the platter's range errors taken about their mean: the platter gives the axis's
        direction and not its origin (with the lidar's range model, a platter of another finish
        than the fixtures reads at another range)"""
        self.free = free
        self.base = x6.copy()
        self.swa = np.sqrt(matched.wa)
        self.swb = np.sqrt(matched.wb)
        self._nq: tuple[FloatArray, FloatArray, FloatArray, FloatArray] | None = None
        self._corrections = Kept()
        self.platter_dir = np.zeros((0, 3))
        self.point_dir = np.zeros((0, 3))
        if matched.one_sided:
            # each point's ray: its residual is measured along it (see _target_residuals)
            self.point_dir = _unit(matched.pb)
        self.ray_a = _unit(matched.pa)
        self.ray_b = self.point_dir if matched.one_sided else _unit(matched.pb)
        self.platter_weight = platter_weight
        self.shape_p = np.zeros(0)
        if platter is not None and platter.shape[0]:
            # each platter return's ray (the lidar sits at the origin of L)
            self.platter_dir = _unit(platter)
            self.shape_p = incidence_shape(self.platter_dir @ _rotation(x6)[:, 0])
        self.shape_a, self.shape_b = self._incidence(x6)
        if platter is not None and platter.shape[0]:
            self.platter_weight = platter_weight * self._platter_scale(x6, noise)

    def _incidence(self, x6: FloatArray) -> tuple[FloatArray, FloatArray]:
        """The incidence bias's shape (:func:`~calstation.engine.rangemodel.incidence_shape`)
        of each match's two points under ``x6``: A's point on A's plane, B's on the plane it is
        measured against (A's when one-sided, else its own). Held through the inner solve: the
        planes' normals do not move with t, and H turns them by less than a degree."""
        R = _rotation(x6)
        aa, ab, _, bb = self._normals_in_q()
        a = incidence_shape(rowdot(self.ray_a, aa @ R.T))
        b = incidence_shape(rowdot(self.ray_b, (ab if self.m.one_sided else bb) @ R.T))
        return a, b

    def _corrected(self, which: str, x6: FloatArray) -> FloatArray:
        """The matches' points of ``which`` half (``"a"``, ``"b"``) or the platter's returns
        (``"platter"``) corrected by the range terms of ``x6`` (:func:`~calstation.engine.
        rangemodel.correct_vector`, with their incidence shapes), kept while those terms stay
        the same: where the fine-tuning holds them (with the lidar's range model, its spin
        target does), the points are corrected once per inner solve rather than at every
        evaluation."""
        points, shape = {"a": (self.m.pa, self.shape_a), "b": (self.m.pb, self.shape_b),
                         "platter": (self.platter, self.shape_p)}[which]
        assert points is not None
        return self._corrections.get(which, x6[OFFSET:].tobytes(),
                                     lambda: correct_vector(points, x6, shape))

    def _platter_scale(self, x6: FloatArray, noise: float) -> float:
        """Weight of the platter residuals (range errors, m) relative to the target's: the
        ratio of their noise, so that both groups count by their information. The target's
        noise is the RMS of its residuals under the start H of this inner solve; the
        platter's is the range noise (the RMS of its own residuals when it is unknown), at
        least :data:`PLATTER_NOISE_FLOOR`."""
        if self.m.pa.shape[0] == 0:
            return 1.0
        target = self._target_residuals(x6)
        rms_target = float(np.sqrt(np.mean(target**2)))
        if not (math.isfinite(noise) and noise > 0):
            along = self._platter_along_rays(x6)
            noise = float(np.sqrt(np.mean(along**2)))
        noise = max(noise, PLATTER_NOISE_FLOOR)
        if not rms_target > 0:
            return 1.0
        return rms_target / noise

    def _platter_along_rays(self, x6: FloatArray) -> FloatArray:
        """(P,) each platter return's range error against the plane x_P = 0 under H (m): its
        height above the plane over the axis component of its ray."""
        assert self.platter is not None
        a = _rotation(x6)[:, 0]
        cos_incidence = _clip_away_from_zero(self.platter_dir @ a, GRAZING_PLATTER)
        corrected = self._corrected("platter", x6)
        out: FloatArray = ((corrected - x6[:3]) @ a) / cos_incidence
        return out

    def row_blocks(self) -> NDArray[np.int64]:
        """(rows,) the spatial block of each residual, in the order of :meth:`residuals`."""
        b = self.m.block
        parts = [b] if self.m.one_sided else [b, b]
        if self.platter is not None and self.platter.shape[0]:
            parts.append(block_ids(self.platter, SIGMA_BLOCK) + (int(b.max(initial=-1)) + 1))
        return np.concatenate(parts)

    def full(self, x: FloatArray) -> FloatArray:
        x6 = self.base.copy()
        x6[self.free] = x
        return x6

    def solution(self, x: FloatArray) -> Solution:
        """The residuals and the Jacobian at ``x`` in full, as the covariance reads them
        (``fun``, ``jac``, ``x``)."""
        return Solution(x=x, fun=self.residuals(x), jac=self.jacobian(x))

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

    def _target_residuals(self, x6: FloatArray) -> FloatArray:
        """The target's residuals (m): each match's point against the other half's local
        plane (both ends, or only B's point when one-sided)."""
        m = self.m
        R = _rotation(x6)
        aa, ab, ba, bb = self._normals_in_q()
        ua = self._corrected("a", x6) - x6[:3]
        ub = self._corrected("b", x6) - x6[:3]
        # point of B against A's local plane, and point of A against B's local plane
        ra = self.swa * (rowdot(ua, aa @ R.T) - rowdot(ub, ab @ R.T) + m.oa)
        if m.one_sided:
            # the range error of B's point against A's plane: its distance over the cosine of
            # its ray with the plane, which H turns (the noise's share of the distance)
            c = _clip_away_from_zero(rowdot(self.point_dir, ab @ R.T), GRAZING_TARGET)
            out: FloatArray = ra / np.abs(c)
            return out
        rb = self.swb * (rowdot(ua, ba @ R.T) - rowdot(ub, bb @ R.T) - m.ob)
        return np.concatenate([ra, rb])

    def residuals(self, x: FloatArray) -> FloatArray:
        """The target's residuals (m), then the platter's: each platter return's range error
        against the plane x_P = 0, measured along its ray and weighted (see
        :meth:`_platter_scale`). Along the ray, the range noise adds the same variance whatever
        H; the height x_P would let H trade fit for noise (the noise's share of x_P is its
        ray's axis component, which ry and rz turn), which biased ry by tens of per cent of
        its value."""
        x6 = self.full(x)
        parts = [self._target_residuals(x6)]
        if self.platter is not None and self.platter.shape[0]:
            along = self._platter_along_rays(x6)
            if self.platter_level_free:
                along = along - along.mean()
            parts.append(self.platter_weight * along)
        return np.concatenate(parts)

    def jacobian(self, x: FloatArray) -> FloatArray:
        """(rows, free) derivatives of :meth:`residuals`, in closed form (the rotation's
        derivatives by central differences of the 3×3 matrix, exact to ~1e-12)."""
        x6 = self.full(x)
        R = _rotation(x6)
        n = self.m.pa.shape[0]
        end = n if self.m.one_sided else 2 * n  # the platter's rows follow the target's
        platter = 0 if self.platter is None else self.platter.shape[0]
        J = np.empty((end + platter, len(self.free)))
        self._target_jacobian(x6, R, J[:end])
        self._platter_jacobian(x6, R, J[end:])
        if self.platter_level_free and platter:
            J[end:] -= J[end:].mean(axis=0)
        return J

    def follows(self, x: FloatArray, held: list[int]) -> dict[str, dict[str, float]]:
        """How the solution ``x`` (of the free parameters) would move per unit of each of the
        ``held`` parameters (indices of :data:`~calstation.engine.rangemodel.ESTIMATED_NAMES`):
        dx = −J⁺·J_held, the least-squares response to its column."""
        if not held:
            return {}
        free = self.free
        J = self.jacobian(x)
        x_all = self.full(x)
        try:
            self.free = list(held)
            columns = self.jacobian(x_all[held])
        finally:
            self.free = free
        dx = -np.linalg.lstsq(J, columns, rcond=None)[0]
        return {ESTIMATED_NAMES[h]: {ESTIMATED_NAMES[i]: float(dx[k, j])
                                     for k, i in enumerate(free)}
                for j, h in enumerate(held)}

    def encoder_follows(self, x: FloatArray) -> dict[str, dict[str, float]]:
        """How the solution ``x`` would move per radian of each coefficient of the encoder's
        angle error (:data:`~calstation.engine.encoder.HARMONICS`): dx = −J⁺·∂r/∂c. A
        match's residuals depend on its two points' platter angles alone, so ∂r/∂c is
        ∂r/∂φa·e_c(φa) + ∂r/∂φb·e_c(φb), each ∂r/∂φ one central difference of that half's
        angles turned alike (the platter's residuals do not turn with them)."""
        from dataclasses import replace

        from calstation.engine.encoder import HARMONICS, STEP, basis, turned

        m = self.m
        rows = m.pa.shape[0] if m.one_sided else 2 * m.pa.shape[0]
        J = self.jacobian(x)
        kept, nq = self.m, self._nq
        columns = np.zeros((J.shape[0], len(HARMONICS)))
        try:
            for c, s in ((m.ca, m.sa), (m.cb, m.sb)):
                moved = []
                for sign in (1.0, -1.0):
                    c2, s2 = turned(c, s, sign * STEP)
                    self.m = (replace(kept, ca=c2, sa=s2) if c is m.ca
                              else replace(kept, cb=c2, sb=s2))
                    self._nq = None
                    moved.append(self.residuals(x)[:rows])
                by_angle = (moved[0] - moved[1]) / (2.0 * STEP)
                harmonics = basis(c, s)
                if not m.one_sided:
                    harmonics = np.vstack([harmonics, harmonics])
                columns[:rows] += by_angle[:, None] * harmonics
        finally:
            self.m, self._nq = kept, nq
        dx = -np.linalg.solve(J.T @ J, J.T @ columns)
        return {h: {ESTIMATED_NAMES[i]: float(dx[k, j]) for k, i in enumerate(self.free)}
                for j, h in enumerate(HARMONICS)}

    def _target_jacobian(self, x6: FloatArray, R: FloatArray, out: FloatArray) -> None:
        """The target's rows of :meth:`jacobian`, written into ``out``."""
        m = self.m
        aa, ab, ba, bb = self._normals_in_q()
        pa = self._corrected("a", x6)
        pb = self._corrected("b", x6)
        ua, ub = pa - x6[:3], pb - x6[:3]
        n = aa.shape[0]
        # ∂/∂t: the same three columns for every translation
        ta = -self.swa[:, None] * ((aa - ab) @ R.T)
        tb = -self.swb[:, None] * ((ba - bb) @ R.T)
        if m.one_sided:
            # the residual r/|c| of _target_residuals: (J_r·|c| − r·∂|c|)/c², where a clipped
            # cosine does not move with H
            r_plane = self.swa * (rowdot(ua, aa @ R.T) - rowdot(ub, ab @ R.T) + m.oa)
            c_free = rowdot(self.point_dir, ab @ R.T)
            c_pt = _clip_away_from_zero(c_free, GRAZING_TARGET)
            c_turns = c_free == c_pt
            s_pt = np.abs(c_pt)
            ta = ta / s_pt[:, None]
        # a range term moves each point along its own ray: ∂p/∂b = −ray/(1 + k),
        # ∂p/∂k = −p/(1 + k), the same chain as −∂t for that point alone
        scale = 1.0 + (float(x6[SCALE]) if x6.size > SCALE else 0.0)
        for col, i in enumerate(self.free):
            if i < 3:
                out[:n, col] = ta[:, i]
                if not m.one_sided:
                    out[n:, col] = tb[:, i]
                continue
            if i >= OFFSET:
                va, vb = {OFFSET: (self.ray_a, self.ray_b), SCALE: (pa, pb),
                          INCIDENCE: (self.ray_a * self.shape_a[:, None],
                                      self.ray_b * self.shape_b[:, None])}[i]
                da = -self.swa * (rowdot(aa @ R.T, va) - rowdot(ab @ R.T, vb)) / scale
                if m.one_sided:
                    out[:n, col] = da / s_pt
                else:
                    out[:n, col] = da
                    out[n:, col] = -self.swb * (
                        rowdot(ba @ R.T, va) - rowdot(bb @ R.T, vb)) / scale
                continue
            dR = rotation_derivative(x6, i)
            va, vb = ua @ dR, ub @ dR
            out[:n, col] = self.swa * (rowdot(va, aa) - rowdot(vb, ab))
            if m.one_sided:
                ds = rowdot(self.point_dir, ab @ dR.T) * c_turns * c_pt / s_pt
                out[:n, col] = (out[:n, col] * s_pt - r_plane * ds) / s_pt**2
            else:
                out[n:, col] = self.swb * (rowdot(va, ba) - rowdot(vb, bb))

    def _platter_jacobian(self, x6: FloatArray, R: FloatArray, out: FloatArray) -> None:
        """The platter's rows of :meth:`jacobian`, written into ``out``: of its range error
        h/c, h = a·(p − t) the return's height and c = a·d its ray's cosine with the axis a
        (a clipped cosine does not move with H)."""
        platter = self.platter if self.platter is not None else np.zeros((0, 3))
        w = self.platter_weight
        a = R[:, 0]
        corrected = (self._corrected("platter", x6) if self.platter is not None
                     else correct_vector(platter, x6, self.shape_p))
        up = corrected - x6[:3]
        h = up @ a
        c_free = self.platter_dir @ a
        c = _clip_away_from_zero(c_free, GRAZING_PLATTER)
        turns = c == c_free
        scale = 1.0 + (float(x6[SCALE]) if x6.size > SCALE else 0.0)
        for col, i in enumerate(self.free):
            if i < 3:
                out[:, col] = -w * a[i] / c
                continue
            if i >= OFFSET:
                along = {OFFSET: self.platter_dir, SCALE: corrected,
                         INCIDENCE: self.platter_dir * self.shape_p[:, None]}[i]
                out[:, col] = -w * (along @ a) / (scale * c)
                continue
            da = rotation_derivative(x6, i)[:, 0]
            out[:, col] = w * ((up @ da) * c - h * (self.platter_dir @ da) * turns) / c**2


class _Reduced:
    """The inner solve of one outer iteration on n + 1 rows instead of millions.

    With J₀ = Q·R (thin QR) at the start x₀, ``[Qᵀ·r(x), ‖r₀ − Q·Qᵀ·r₀‖]`` has the full
    problem's gradient direction to first order (the part of r outside the span of J₀ does not
    move with x) and its cost at x₀, so TRF takes the same steps and its tolerances keep their
    meaning, while its linear algebra runs on n + 1 rows. The residuals are still evaluated in
    full (closed form); the Jacobian is J₀'s, R, at every x of the inner solve (chord steps):
    within one outer iteration H moves by millimetres and milliradians, which change J by as
    little, and the outer loop re-matches and re-linearises anyway. On the paper bench's nine
    scenes, from the initial calibration and from three far starts each, the estimates were
    within 0.005σ of those with the Jacobian evaluated at every step, 10–16 % sooner. The σ
    comes from the full Jacobian at the solution (:meth:`_Problem.solution`).
    """

    def __init__(self, problem: _Problem, x0: FloatArray) -> None:
        self.problem = problem
        J0 = problem.jacobian(x0)
        r0 = problem.residuals(x0)
        self.Q, self.R = np.linalg.qr(J0)
        rest = r0 - self.Q @ (self.Q.T @ r0)
        self.rest = float(np.sqrt(rest @ rest))
        # TRF evaluates them at x0 first, and the stage its cost where TRF ended: the last
        # full evaluation is kept with its x
        self._last = Kept()
        self._last.get("residuals", x0.tobytes(), lambda: r0)

    def full_residuals(self, x: FloatArray) -> FloatArray:
        """The problem's residuals at ``x`` (the last evaluation's when at the same x)."""
        return self._last.get("residuals", x.tobytes(), lambda: self.problem.residuals(x))

    def residuals(self, x: FloatArray) -> FloatArray:
        return np.append(self.Q.T @ self.full_residuals(x), self.rest)

    def jacobian(self, x: FloatArray) -> FloatArray:
        """Qᵀ·J₀ = R, the same at every ``x`` (the rest's row does not move to first order)."""
        return np.vstack([self.R, np.zeros((1, self.R.shape[1]))])


def _clip_away_from_zero(c: FloatArray, least: float) -> FloatArray:
    """``c`` with its magnitude at least ``least`` (its sign kept; 0 counts as positive): a
    ray's cosine with a plane, which only a grazing ray brings near 0."""
    out: FloatArray = np.where(c < 0, np.minimum(c, -least), np.maximum(c, least))
    return out


def _unit(p: FloatArray) -> FloatArray:
    """(N, 3) each row's unit vector: the ray of a return in L (the lidar at the origin)."""
    out: FloatArray = p / np.maximum(np.linalg.norm(p, axis=1, keepdims=True), 1e-9)
    return out


def _free(gauge_ty: bool, range_terms: list[int] | None = None) -> list[int]:
    """The free parameters' indices: H's (ty held under the ``ty`` gauge), then the range
    terms estimated (:func:`calstation.engine.rangemodel.estimated_indices`)."""
    names = ["tx", "tz", "ry", "rz"] if gauge_ty else ["tx", "ty", "tz", "ry", "rz"]
    return [IDX[n] for n in names] + list(range_terms or [])


def _bounds(
    x6: FloatArray, start6: FloatArray, free: list[int], settings: PeriodicitySettings
) -> tuple[FloatArray, FloatArray]:
    tb = settings.translation_bound
    rb = math.radians(settings.rotation_bound_deg)
    ryb = math.radians(settings.ry_bound_deg)
    lo, hi = [], []
    for i in free:
        if i in (IDX["ry"], OFFSET, SCALE, INCIDENCE):
            # never re-centred: ry and the range terms are weakly observable and would walk to
            # a moving bound
            half = {IDX["ry"]: ryb, OFFSET: RANGE_OFFSET_BOUND, SCALE: RANGE_SCALE_BOUND,
                    INCIDENCE: INCIDENCE_BOUND}[i]
            lo.append(start6[i] - half)
            hi.append(start6[i] + half)
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
    q = (correct_vector(p_static, x6) - x6[:3]) @ _rotation(x6)
    r = np.hypot(q[:, 1], q[:, 2])
    keep = (np.abs(q[:, 0]) <= tolerance) & (r <= radius)
    return p_static[keep]
