"""Periodicity-constrained fine-tuning (paper §III-B-2, §IV-C; DESIGN §5) with calstation's
robustness additions.

Every surface point of the spin target is seen twice per revolution: once in the half-turn
φ ∈ [0, π) and once in [π, 2π). With the right H both half-turn reconstructions in frame D
coincide. The cost is the weighted point-to-plane distance between mutual nearest neighbours of
the two halves, ``Σ w·(n·(x − x′))²`` with normals from the nearest points and the planarity
weight ``w = 2(λ2 − λ3)/(λ1 + λ2 + λ3)``, minimised by SciPy's TRF.

What calstation adds (docs/algorithms.md):

- **Static-point removal.** Returns that stay at the same place in L over the whole scan (the
  platter ring, the background, any face of revolution) carry no periodicity information; they
  are found per azimuth bin, independently of H, and dropped. Points within a few mm of the
  platter top are dropped too once H is good enough to tell them apart.
- **Coarse-to-fine schedule.** A centroid alignment of the two half-turns (stage 0), then four
  matching stages whose cell size, match radius and normal neighbourhood shrink (20 → 1 mm), so
  matching converges from starts 100–200 mm and 1–2° off. Cells are cut on the sensor grid
  (platter angle × azimuth) and average the raw returns (in L) with their platter angles:
  unbiased by the range noise, and computed once per stage.
- **Point-to-local-plane residuals, symmetric.** Each match contributes the distance of each end
  to the plane fitted around the other end.
- **Bounds.** tx, ty, tz and rz are bounded ±``translation_bound``/±``rotation_bound_deg``
  around the current estimate (re-centred every outer iteration: they are sharp in the cost);
  ry is bounded ±``ry_bound_deg`` around its *start* and never re-centred (the cost is nearly
  flat in ry; a re-centred bound lets it walk away).
- **Gauge.** The periodicity cost cannot see a shift along the axis. ``gauge: platter`` (the
  default) fixes it with the platter: the top surface of the platter is the plane x_P = 0, so
  the static platter returns add the residual x_P = a·(p_L − t) = 0, which also sharpens rz. The
  coarse stages hold ty fixed (the paper's fix) until the platter is identified.
  ``gauge: ty`` is the paper's fix throughout.
- **Covariance** σ²·(JᵀJ)⁻¹ from the final Jacobian with σ² from the residuals, matches per
  iteration, per-stage costs and timings in the diagnostics.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from calstation.engine.frames import (
    PARAMETER_NAMES,
    Extrinsics,
    FloatArray,
    euler_to_matrix,
    lidar_to_polar,
)
from calstation.engine.neighbours import knn, local_planes, mutual_neighbours, pair, tree
from calstation.engine.result import CalibrationResult
from calstation.engine.settings import DEFAULT_PLATTER_RADIUS, PeriodicitySettings
from calstation.engine.spinscan import (
    SpinScan,
    from_recording,
    prepare,
    static_mask as static_mask,  # re-exported: shape and the bench use it
)
from calstation.errors import FineTuningError

if TYPE_CHECKING:
    from calstation.engine.scan import Scan

Progress = Callable[[str, float], None]

IDX = {name: i for i, name in enumerate(PARAMETER_NAMES)}
MIN_MATCHES = 50
"""Fewest matched cells between the two half-turns an iteration accepts."""


@dataclass(frozen=True)
class Stage:
    """One step of the coarse-to-fine schedule (metres)."""

    voxel: float
    match_radius: float
    normal_neighbours: int
    platter_drop: float | None
    """drop points with x_P below this (None: only static points are dropped)"""
    use_platter: bool
    """add the platter residual (gauge ``platter``) in this stage"""
    max_points: int | None
    """random subset of raw returns per half-turn used in this stage (None: all)"""
    max_outer: int
    """outer iterations (re-matching) at most"""
    hold_ry: bool = False
    """keep ry at its current value (coarse cells cannot resolve it and let it wander)"""


def schedule(settings: PeriodicitySettings, final_voxel: float = 0.001) -> list[Stage]:
    """The stages for ``settings``: four coarse-to-fine stages, or the paper's single stage.

    ``final_voxel`` (m) is the cell size of the last stage, chosen from the scan's noise and
    density by :func:`final_cell_size`. ry is held in every stage but the last: coarse cells
    and the few hundred matches of the 5 mm stage cannot resolve it and throw it to its bound.
    """
    k = settings.normal_neighbours
    platter = settings.gauge == "platter"
    if not settings.coarse_to_fine:
        return [
            Stage(
                final_voxel,
                max(settings.match_distance, 4 * final_voxel),
                max(8, k // 2),
                0.004,
                platter,
                None,
                settings.max_outer,
            )
        ]
    n = settings.max_outer
    fine = max(final_voxel, 0.001)
    return [
        Stage(
            0.020, min(0.12, settings.match_distance), max(8, k // 4), None, False, 60_000, n, True
        ),
        Stage(
            0.010,
            min(0.05, settings.match_distance),
            max(12, k // 3),
            0.008,
            platter,
            120_000,
            n,
            True,
        ),
        Stage(
            max(0.005, fine),
            min(0.02, settings.match_distance),
            max(16, k // 2),
            0.005,
            platter,
            300_000,
            n,
            True,
        ),
        Stage(
            fine,
            min(4 * fine, settings.match_distance),
            max(8, k // 2),
            0.004,
            platter,
            None,
            max(n, FINAL_MAX_OUTER),
        ),
    ]


FINAL_MAX_OUTER = 30
"""Outer iterations allowed in the last stage: it stops on the parameter step, not the cost."""

CELL_SIZES = (0.001, 0.0015, 0.002, 0.0025, 0.003, 0.004, 0.005)
"""Candidate cell sizes of the last stage (m), smallest first."""

CELL_NOISE_RATIO = 1.0 / 3.0
"""The last stage's cells must average the range noise down to this fraction of their size."""


def final_cell_size(
    halves_p_L: list[FloatArray],
    halves_phi: list[FloatArray],
    noise: float,
    halves_polar: list[tuple[FloatArray, FloatArray]] | None = None,
) -> float:
    """The smallest cell size of :data:`CELL_SIZES` whose cells average the range noise down to
    :data:`CELL_NOISE_RATIO` of their size (m).

    Mutual nearest neighbours between the two half-turns prefer pairs whose noise cancels their
    misalignment; when a cell's noise (σ/√returns) is comparable to the cell spacing, each outer
    iteration recovers only a few per cent of an ry error, and ry stays biased (docs/algorithms.md).
    The count per cell is the median over the target's cells of both halves. ``halves_polar``:
    the (range, azimuth) of each half's returns, when already known.
    """
    if not math.isfinite(noise) or noise <= 0:
        return CELL_SIZES[0]
    polar = halves_polar or [lidar_to_polar(p) for p in halves_p_L]
    for size in CELL_SIZES:
        counts = np.concatenate(
            [
                _cell_counts(r, a, ph, size)
                for (r, a), ph in zip(polar, halves_phi, strict=True)
                if ph.size
            ]
            or [np.zeros(0, dtype=np.int64)]
        )
        per_cell = float(np.median(counts)) if counts.size else 1.0
        if noise / math.sqrt(per_cell) <= CELL_NOISE_RATIO * size:
            return size
    return CELL_SIZES[-1]


def _cell_keys(
    rng: FloatArray, az: FloatArray, phi: FloatArray, size: float, radius_ref: float
) -> NDArray[np.int64]:
    """(N,) cell index of each return on the sensor grid (platter angle × azimuth)."""
    az_step = size / float(np.median(rng))
    phi_step = size / radius_ref
    ia = np.floor(az / az_step).astype(np.int64)
    ip = np.floor(phi / phi_step).astype(np.int64)
    ia -= ia.min()
    ip -= ip.min()
    out: NDArray[np.int64] = ip * (int(ia.max()) + 1) + ia
    return out


def _groups(key: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """(inverse, counts) of the distinct values of ``key`` (≥ 0), in ascending order: by a
    dense count when the keys are few (no sort over millions of returns), else ``np.unique``."""
    top = int(key.max()) + 1
    if top <= 4 * key.size + 1_000_000:
        dense = np.bincount(key, minlength=top)
        used = np.flatnonzero(dense)
        index = np.zeros(top, dtype=np.int64)
        index[used] = np.arange(used.size)
        return index[key], dense[used]
    _, inv, counts = np.unique(key, return_inverse=True, return_counts=True)
    return inv.reshape(-1), counts


def _cell_counts(
    rng: FloatArray, az: FloatArray, phi: FloatArray, size: float, radius_ref: float = 0.15
) -> NDArray[np.int64]:
    if rng.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    return _groups(_cell_keys(rng, az, phi, size, radius_ref))[1]


# --- geometry helpers ------------------------------------------------------------------------
def _rotation(x6: FloatArray) -> FloatArray:
    return euler_to_matrix(float(x6[3]), float(x6[4]), float(x6[5]))


def to_dynamic(
    p_L: FloatArray, cos_phi: FloatArray, sin_phi: FloatArray, x6: FloatArray
) -> FloatArray:
    """(N, 3) points in L with their platter angles (as cos, sin) → (N, 3) in D, for H = x6."""
    q = (p_L - x6[:3]) @ _rotation(x6)
    y = cos_phi * q[:, 1] + sin_phi * q[:, 2]
    z = -sin_phi * q[:, 1] + cos_phi * q[:, 2]
    return np.column_stack([q[:, 0], y, z])


def sensor_cells(
    p_L: FloatArray,
    phi: FloatArray,
    size: float,
    *,
    radius_ref: float = 0.15,
    polar: tuple[FloatArray, FloatArray] | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Average returns over cells of the sensor grid (platter angle × azimuth), ~``size`` m wide.

    Cells are cut in (φ, α), which carry no range noise, so the averages are unbiased (a voxel
    grid in D would select points by their noisy position and pull the averages toward voxel
    centres). A cell spans ``size / radius_ref`` of platter angle and ``size / median range`` of
    azimuth; cells whose ranges spread more than 4·``size`` (a depth edge) are dropped.
    ``polar``: the returns' (range, azimuth), when already known. Returns ((C, 3) mean returns
    in L, (C,) mean φ).
    """
    if p_L.shape[0] == 0:
        return p_L, phi
    rng, az = lidar_to_polar(p_L) if polar is None else polar
    inv, counts = _groups(_cell_keys(rng, az, phi, size, radius_ref))
    m = counts.size
    mean = np.zeros((m, 3))
    for j in range(2):
        mean[:, j] = np.bincount(inv, weights=p_L[:, j], minlength=m) / counts
    ph = np.bincount(inv, weights=phi, minlength=m) / counts
    r_mean = np.bincount(inv, weights=rng, minlength=m) / counts
    r_sq = np.bincount(inv, weights=rng * rng, minlength=m) / counts
    spread = np.sqrt(np.maximum(r_sq - r_mean**2, 0.0))
    keep = spread <= max(4.0 * size, 0.004)
    return mean[keep], ph[keep]


# --- the problem ------------------------------------------------------------------------------
@dataclass
class _Half:
    """Returns (or cells) of one half-turn; ``rng``/``az`` their polar coordinates if known."""

    p_L: FloatArray
    phi: FloatArray
    rng: FloatArray | None = None
    az: FloatArray | None = None

    def take(self, idx: NDArray[np.int64] | NDArray[np.bool_]) -> _Half:
        polar = self.rng is not None and self.az is not None
        return _Half(
            self.p_L[idx],
            self.phi[idx],
            self.rng[idx] if polar and self.rng is not None else None,
            self.az[idx] if polar and self.az is not None else None,
        )

    def cells(self, size: float) -> _Half:
        polar = None if self.rng is None or self.az is None else (self.rng, self.az)
        return _Half(*sensor_cells(self.p_L, self.phi, size, polar=polar))


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


def _subset(half: _Half, n: int | None, rng: np.random.Generator) -> _Half:
    if n is None or half.p_L.shape[0] <= n:
        return half
    return half.take(np.sort(rng.choice(half.p_L.shape[0], n, replace=False)))


def static_samples(static: NDArray[np.int64], n: int = 150_000, seed: int = 0) -> NDArray[np.int64]:
    """A fixed random subset of at most ``n`` of the indices ``static`` of static returns.

    Raw returns rather than per-bin averages: grouping by noisy range would bias the averages.
    """
    if static.shape[0] <= n:
        return static
    rng = np.random.default_rng(seed)
    return static[np.sort(rng.choice(static.shape[0], n, replace=False))]


# --- the algorithm ---------------------------------------------------------------------------
def periodicity_fine_tune_points(
    p_L: FloatArray,
    phi: FloatArray,
    start: Extrinsics,
    settings: PeriodicitySettings = PeriodicitySettings(),
    *,
    platter_radius: float = DEFAULT_PLATTER_RADIUS,
    progress: Progress | None = None,
    stages: int | None = None,
) -> CalibrationResult:
    """Periodicity fine-tuning on the returns of one spin scan.

    ``p_L`` (N, 3) returns in frame L (metres), ``phi`` (N,) their platter angles (rad,
    unwrapped or not). ``start`` is the starting H; rx is held at 0. ``stages``: run only the
    first few stages of the schedule (a coarse alignment; None: all). Returns a
    :class:`CalibrationResult` (strategy ``"periodicity"``, cost = mean weighted squared
    point-to-plane distance in m² at the last stage).
    """
    p_L = np.asarray(p_L, dtype=np.float64)
    phi = np.asarray(phi, dtype=np.float64).reshape(-1)
    if p_L.ndim != 2 or p_L.shape[1] != 3 or p_L.shape[0] != phi.shape[0]:
        raise FineTuningError(
            f"periodicity needs (N, 3) returns and (N,) angles, got {p_L.shape} and {phi.shape}"
        )
    return periodicity_fine_tune_scan(
        prepare(p_L, phi),
        start,
        settings,
        platter_radius=platter_radius,
        progress=progress,
        stages=stages,
    )


def _whole_revolutions(scan: SpinScan) -> NDArray[np.bool_]:
    """(N,) the returns of the whole revolutions of the scan, so that every half-turn is seen
    equally often; a clear error when the scan holds less than one."""
    if scan.n_points < 1000:
        raise FineTuningError(
            f"the spin scan has only {scan.n_points} valid returns; periodicity needs a full "
            "revolution of the spin target"
        )
    lo = float(np.nanmin(scan.phi))
    span = float(np.nanmax(scan.phi)) - lo
    if span < 2 * math.pi * 0.98:
        raise FineTuningError(
            f"the spin scan covers {math.degrees(span):.0f}° of platter rotation; periodicity "
            "needs one full revolution (360°)"
        )
    revolutions = max(1, math.floor(span / (2 * math.pi) + 0.02))
    out: NDArray[np.bool_] = scan.phi < lo + revolutions * 2 * math.pi
    return out


def _split(
    scan: SpinScan, keep: NDArray[np.bool_], start6: FloatArray, platter_radius: float
) -> tuple[list[_Half], list[_Half], FloatArray]:
    """The two half-turns of the moving returns, the two half-turns of all returns, and a
    subset of the static returns, within a generous region around the platter under the start.

    The last stage keeps the static returns too and drops the platter by the height of its
    cells: the static test decides per noisy return, and near the target's foot it would keep
    the returns whose noise moved them off the platter's range (a selection on the noise).
    """
    R = _rotation(start6)
    t_P = start6[:3] @ R
    # x_P first, then the radius on what is left; the returns lie in the scan plane (z_L = 0)
    x_P = scan.p_L[:, :2] @ R[:2, 0] - t_P[0]
    idx = np.flatnonzero(keep & (x_P > -0.2) & (x_P < 0.6))
    yz = scan.p_L[idx, :2] @ R[:2, 1:] - t_P[1:]
    idx = idx[np.hypot(yz[:, 0], yz[:, 1]) < platter_radius + 0.25]
    phi_w = np.mod(scan.phi[idx], 2 * math.pi)
    first = phi_w < math.pi
    moving = ~scan.static[idx]

    def half(sel: NDArray[np.bool_]) -> _Half:
        j = idx[sel]
        return _Half(scan.p_L[j], phi_w[sel], scan.rng[j], scan.az[j])

    halves_all = [half(first), half(~first)]
    halves = [half(first & moving), half(~first & moving)]
    static_idx = np.flatnonzero(keep & scan.static)
    p_static = scan.p_L[static_samples(static_idx)]
    if min(h.p_L.shape[0] for h in halves) < 500:
        raise FineTuningError(
            f"too few moving returns on the spin target ({halves[0].p_L.shape[0]} and "
            f"{halves[1].p_L.shape[0]} in the two half-turns); is the spin target on the platter?"
        )
    return halves, halves_all, p_static


class _Run:
    """The outer iterations of the stages: matching, solving, and what they leave behind."""

    def __init__(
        self,
        start6: FloatArray,
        p_static: FloatArray,
        settings: PeriodicitySettings,
        platter_radius: float,
        progress: Progress | None,
        n_stages: int,
    ) -> None:
        self.start6 = start6
        self.p_static = p_static
        self.settings = settings
        self.platter_radius = platter_radius
        self.progress = progress
        self.n_stages = n_stages
        self.history: list[dict[str, Any]] = []
        self.last: tuple[FloatArray, _Problem] | None = None
        """the last inner solution and its problem"""
        self.outer = 0
        self.cost = math.nan
        self.timings = {"cells": 0.0, "match": 0.0, "solve": 0.0}

    def stage(self, s_i: int, stage: Stage, match: _Matcher, x6: FloatArray) -> FloatArray:
        """Iterate one stage from ``x6``; returns the H (as a vector) it ends on."""
        settings = self.settings
        gauge_ty = settings.gauge == "ty" or not stage.use_platter
        free = [i for i in _free(gauge_ty) if not (stage.hold_ry and i == IDX["ry"])]
        for outer in range(stage.max_outer):
            if self.progress is not None:
                self.progress(
                    f"periodicity stage {s_i + 1}/{self.n_stages} ({stage.voxel * 1e3:.0f} mm)",
                    (s_i + outer / stage.max_outer) / self.n_stages,
                )
            t0 = time.perf_counter()
            matched, n_pts = match(x6)
            platter = self._platter(stage, x6)
            t1 = time.perf_counter()
            n_matches = matched.pa.shape[0]
            if n_matches < MIN_MATCHES:
                raise FineTuningError(
                    f"periodicity stage {s_i + 1}: only {n_matches} matches between the two "
                    f"half-turns (voxel {stage.voxel * 1e3:.0f} mm, radius "
                    f"{stage.match_radius * 1e3:.0f} mm); the start is too far off or the spin "
                    "target is not seen in both half-turns"
                )
            problem = _Problem(matched, platter, 1.0, free, x6)
            lo, hi = _bounds(x6, self.start6, free, settings)
            reduced = _Reduced(problem, x6[free])
            res = least_squares(
                reduced.residuals,
                x6[free],
                jac=reduced.jacobian,
                bounds=(lo, hi),
                method="trf",
                x_scale=np.full(len(free), 1e-3),
                xtol=settings.xtol,
                ftol=settings.ftol,
                max_nfev=settings.max_nfev,
            )
            self.timings["match"] += t1 - t0
            self.timings["solve"] += time.perf_counter() - t1
            new6 = problem.full(res.x)
            step = np.abs(new6 - x6)
            x6 = new6
            self.outer += 1
            self.cost = float(np.mean(problem.residuals(res.x) ** 2))
            self.last = (res.x, problem)
            self.history.append(
                {
                    "stage": s_i + 1,
                    "voxel_m": stage.voxel,
                    "points": n_pts,
                    "matches": int(n_matches),
                    "platter_samples": 0 if platter is None else int(platter.shape[0]),
                    "cost": self.cost,
                    "nfev": int(res.nfev),
                }
            )
            if _converged(self.history, outer, step, stage):
                break
        return x6

    def _platter(self, stage: Stage, x6: FloatArray) -> FloatArray | None:
        if not stage.use_platter:
            return None
        platter = _platter_samples(self.p_static, x6, max(0.003, stage.voxel), self.platter_radius)
        if platter.shape[0] < 20:
            raise FineTuningError(
                "gauge 'platter': the platter top is not visible in the spin scan "
                f"({platter.shape[0]} static returns near x_P = 0 under the current estimate); "
                "the start may be too far off (run the coarse stages, or start from the initial "
                "calibration), or the platter is hidden (use gauge: ty)"
            )
        return platter


def periodicity_fine_tune_scan(
    scan: SpinScan,
    start: Extrinsics,
    settings: PeriodicitySettings = PeriodicitySettings(),
    *,
    platter_radius: float = DEFAULT_PLATTER_RADIUS,
    progress: Progress | None = None,
    stages: int | None = None,
) -> CalibrationResult:
    """Periodicity fine-tuning on a prepared :class:`~calstation.engine.spinscan.SpinScan`: as
    :func:`periodicity_fine_tune_points`, without the per-scan preparation (done as the lines
    arrived, or once for several fine-tunings)."""
    t_start = time.perf_counter()
    timings: dict[str, float] = {f"scan_{k}": v for k, v in scan.timings.items()}
    keep = _whole_revolutions(scan)
    start6 = start.with_(rx=0.0).as_vector()
    halves, halves_all, p_static_all = _split(scan, keep, start6, platter_radius)
    noise = scan.noise
    timings["prepare"] = time.perf_counter() - t_start
    final_voxel = final_cell_size(
        [h.p_L for h in halves],
        [h.phi for h in halves],
        noise,
        [(h.rng, h.az) for h in halves if h.rng is not None and h.az is not None],
    )
    schedule_ = schedule(settings, final_voxel)[:stages]
    x6 = start6.copy()
    if settings.coarse_to_fine:
        # keep the centroid alignment only where it helps: the view asymmetry of the two
        # half-turns biases the centroids, so a good start can be better than its result
        centred = _centre_halves(halves, x6, settings, np.random.default_rng(1))
        first = schedule_[0]
        cells = [h.cells(first.voxel) for h in halves]
        if _match(cells, centred, first)[0].pa.shape[0] > _match(cells, x6, first)[0].pa.shape[0]:
            x6 = centred
    rng = np.random.default_rng(0)
    run = _Run(start6, p_static_all, settings, platter_radius, progress, len(schedule_))
    for s_i, stage in enumerate(schedule_):
        t_stage = time.perf_counter()
        source = halves if stage.hold_ry else halves_all
        stage_halves = [_subset(h, stage.max_points, rng).cells(stage.voxel) for h in source]
        run.timings["cells"] += time.perf_counter() - t_stage
        x6 = run.stage(s_i, stage, _Matcher(stage_halves, stage), x6)
        timings[f"stage{s_i + 1}"] = time.perf_counter() - t_stage
    timings.update(run.timings)
    history, last, total_outer, final_cost = run.history, run.last, run.outer, run.cost
    assert last is not None
    x_last, problem = last
    res = problem.solution(x_last)
    sigma_independent = parameter_sigma(res, problem.free)
    covariance = parameter_covariance(res, problem.free, blocks=problem.row_blocks())
    sigma_blocks = sigma_from_covariance(covariance, problem.free)
    inflation = noise_inflation(noise)
    sigma = {k: v * inflation for k, v in sigma_blocks.items()}
    reported_cov = None if covariance is None else covariance * inflation**2
    H = Extrinsics.from_vector(x6)
    timings["total"] = time.perf_counter() - t_start
    if progress is not None:
        progress("periodicity done", 1.0)
    ry_lo = start6[4] - math.radians(settings.ry_bound_deg)
    ry_hi = start6[4] + math.radians(settings.ry_bound_deg)
    at_bound = min(abs(x6[4] - ry_lo), abs(x6[4] - ry_hi)) < math.radians(0.01)
    return CalibrationResult(
        H=H,
        sigma=sigma,
        cost=final_cost,
        iterations=total_outer,
        strategy="periodicity",
        timings=timings,
        diagnostics={
            "gauge": settings.gauge,
            "gauge_note": (
                "origin along the axis fixed by the platter top plane x_P = 0"
                if settings.gauge == "platter"
                else "ty held at its start value (paper §IV-C)"
            ),
            "coarse_to_fine": settings.coarse_to_fine,
            "matches_per_iteration": [h["matches"] for h in history],
            "iterations": history,
            "static_returns": int(scan.static.sum()),
            "range_noise_m": noise,
            "sigma_independent": sigma_independent,
            "sigma_blocks": sigma_blocks,
            "sigma_noise_inflation": inflation,
            "covariance": covariance_record(reported_cov, problem.free),
            "final_cell_m": final_voxel,
            "moving_returns": int((~scan.static).sum()),
            "ry_at_bound": bool(at_bound),
            "ry_bound_rad": [ry_lo, ry_hi],
            "rms_m": math.sqrt(final_cost),
        },
    )


def _converged(history: list[dict[str, Any]], outer: int, step: FloatArray, stage: Stage) -> bool:
    """Stop the outer loop of a stage?

    While ry is held, a stalled cost or a step below the cell's resolution ends the stage. Once
    ry is free the cost is nearly flat in it, so only the parameter step counts: a cost-based
    stop ended the loop while ry was still walking back from a wrong start.
    """
    small_step = (
        step[:3].max() < stage.voxel * 0.02
        and step[5] < math.radians(0.001) * stage.voxel / 0.002
        and step[4] < math.radians(0.002)
    )
    if not stage.hold_ry:
        return bool(small_step)
    prev_cost = history[-2]["cost"] if len(history) > 1 and outer > 0 else math.inf
    cost = history[-1]["cost"]
    return bool(small_step or (outer > 0 and abs(prev_cost - cost) <= 1e-3 * cost))


def _centre_halves(
    halves: list[_Half], x6: FloatArray, settings: PeriodicitySettings, rng: np.random.Generator
) -> FloatArray:
    """Stage 0 (calstation): move tx and tz so that the centroids of the two half-turn
    reconstructions coincide. Smooth, with a basin as wide as the target, it brings starts
    200 mm off within reach of the first matching stage. ty (gauge), ry and rz stay. The caller
    keeps the result only if it gives more first-stage matches than the start."""
    sub = [_subset(h, 20_000, rng) for h in halves]
    cs = [(np.cos(h.phi), np.sin(h.phi)) for h in sub]
    free = [IDX["tx"], IDX["tz"]]

    def fun(x: FloatArray) -> FloatArray:
        v = x6.copy()
        v[free] = x
        a = to_dynamic(sub[0].p_L, *cs[0], v)
        b = to_dynamic(sub[1].p_L, *cs[1], v)
        return np.asarray(a.mean(axis=0) - b.mean(axis=0), dtype=np.float64)

    half = 2.0 * settings.translation_bound * 5
    x0 = x6[free]
    res = least_squares(fun, x0, bounds=(x0 - half, x0 + half), method="trf", max_nfev=30)
    out = x6.copy()
    out[free] = res.x
    return out


class _Matcher:
    """Matches the two half-turns' cells of one stage under successive H.

    The cells, their platter angles and each cell's neighbourhood within its own half are fixed
    for the stage. A neighbourhood (the ``normal_neighbours`` nearest cells in D) is found under
    the H of the stage's first iteration, and again only once H has moved by more than a cell:
    a half-turn's reconstruction deforms smoothly with H, so its neighbourhoods stay while the
    planes through them are refitted at every H. Only the matching between the halves, which
    is what H changes, is searched again at every iteration. Cells well below the platter drop
    (the platter top itself) are left out of the neighbourhoods until they are refreshed.
    """

    def __init__(self, halves: list[_Half], stage: Stage) -> None:
        self.halves = halves
        self.stage = stage
        self.cs = [(np.cos(h.phi), np.sin(h.phi)) for h in halves]
        self.candidates: list[NDArray[np.int64]] = []
        self.frozen: list[FloatArray] = []
        self.trees: list[Any] = []
        self.neighbourhoods: list[NDArray[np.int64]] = []
        self.x6: FloatArray | None = None

    def _stale(self, x6: FloatArray) -> bool:
        if self.x6 is None:
            return True
        moved = np.abs(x6 - self.x6)
        return bool(moved[:3].max() > self.stage.voxel or moved[3:].max() * 0.3 > self.stage.voxel)

    def _refresh(self, d_all: list[FloatArray], x6: FloatArray) -> None:
        drop = self.stage.platter_drop
        # half the drop height: clear of the platter top, with room for H to move
        self.candidates = [
            np.arange(d.shape[0]) if drop is None else np.flatnonzero(d[:, 0] > drop / 2)
            for d in d_all
        ]
        self.frozen = [d[cand] for d, cand in zip(d_all, self.candidates, strict=True)]
        self.trees = [tree(f) for f in self.frozen]
        k = min(self.stage.normal_neighbours, *(f.shape[0] for f in self.frozen))
        self.neighbourhoods = [np.full((f.shape[0], k), -1, dtype=np.int64) for f in self.frozen]
        self.x6 = x6.copy()

    def _neighbourhoods(self, half: int, pos: NDArray[np.int64]) -> NDArray[np.int64]:
        """(Q, k) neighbourhoods (indices into the half's cells) of the candidates ``pos``,
        searched on first use under the H of the last refresh."""
        table = self.neighbourhoods[half]
        missing = np.unique(pos[table[pos, 0] < 0])
        if missing.size:
            found = knn(self.trees[half], self.frozen[half][missing], table.shape[1])
            table[missing] = self.candidates[half][found]
        return table[pos]

    def __call__(self, x6: FloatArray) -> tuple[_Matched, int]:
        """Map both halves to D under H, drop the platter, match, fit the local planes."""
        stage = self.stage
        stale = self._stale(x6)
        (ha, hb), (ca, sa), (cb, sb) = self.halves, self.cs[0], self.cs[1]
        d_all = list(pair(to_dynamic, (ha.p_L, ca, sa, x6), (hb.p_L, cb, sb, x6)))
        if stale:
            self._refresh(d_all, x6)
        kept = []  # positions in the candidates
        for d, cand in zip(d_all, self.candidates, strict=True):
            drop = stage.platter_drop
            kept.append(np.arange(cand.size) if drop is None else np.flatnonzero(d[cand, 0] > drop))
        if min(k.size for k in kept) < MIN_MATCHES:
            raise FineTuningError(
                f"periodicity ({stage.voxel * 1e3:.0f} mm cells): only {kept[0].size} and "
                f"{kept[1].size} cells of the two half-turns lie above the platter under the "
                "current estimate; the start is too far off (run the coarse stages, or start "
                "from the initial calibration) or the spin target is not in view"
            )
        ka, kb = self.candidates[0][kept[0]], self.candidates[1][kept[1]]
        da, db = d_all[0][ka], d_all[1][kb]
        i, j = mutual_neighbours(da, db, stage.match_radius)
        (na, wa, ma), (nb, wb, mb) = pair(
            local_planes,
            (d_all[0], self._neighbourhoods(0, kept[0][i])),
            (d_all[1], self._neighbourhoods(1, kept[1][j])),
        )
        # each residual measures a point against the other half's local plane fit (through its
        # neighbourhood centroid), not against one noisy point; the offset moves with the point
        oa = np.einsum("ij,ij->i", na, ma - da[i])
        ob = np.einsum("ij,ij->i", nb, mb - db[j])
        gi, gj = ka[i], kb[j]
        matched = _Matched(
            ha.p_L[gi],
            ca[gi],
            sa[gi],
            hb.p_L[gj],
            cb[gj],
            sb[gj],
            na,
            nb,
            wa,
            wb,
            oa,
            ob,
            block_ids(da[i], SIGMA_BLOCK),
        )
        return matched, int(da.shape[0] + db.shape[0])


def _match(halves: list[_Half], x6: FloatArray, stage: Stage) -> tuple[_Matched, int]:
    """Match the two half-turns' cells once under H (:class:`_Matcher`)."""
    return _Matcher(halves, stage)(x6)


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


def periodicity_fine_tune(
    recording: Scan,
    start: Extrinsics,
    settings: PeriodicitySettings = PeriodicitySettings(),
    *,
    platter_radius: float = DEFAULT_PLATTER_RADIUS,
    progress: Progress | None = None,
) -> CalibrationResult:
    """Periodicity fine-tuning on a spin-scan
    :class:`~calstation.engine.scan.Scan`."""
    try:
        return periodicity_fine_tune_scan(
            from_recording(recording),
            start,
            settings,
            platter_radius=platter_radius,
            progress=progress,
        )
    except FineTuningError as exc:
        raise FineTuningError(f"{recording.path}: {exc}") from None
