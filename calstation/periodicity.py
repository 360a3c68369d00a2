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
from scipy.spatial import cKDTree

from .errors import FineTuningError
from .frames import PARAMETER_NAMES, Extrinsics, FloatArray, euler_to_matrix, lidar_to_polar
from .recipe import DEFAULT_PLATTER_RADIUS, PeriodicitySettings
from .result import CalibrationResult

if TYPE_CHECKING:
    from .recording import Recording

Progress = Callable[[str, float], None]

IDX = {name: i for i, name in enumerate(PARAMETER_NAMES)}


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


def range_noise(p_L: FloatArray, static: NDArray[np.bool_], *, az_quantum: float = 1e-4) -> float:
    """Range noise σ (m) of the lidar, from the static returns of one scan.

    Static returns (the platter ring, the background) come back at the same range for the same
    azimuth whatever the platter angle, so their spread per azimuth is the range noise. Azimuths
    are grouped in ``az_quantum`` rad (0.1 mm across at 1 m); the σ is 1.4826 × the median of the
    per-azimuth median absolute deviations (robust to mixed pixels). NaN when fewer than 20
    azimuths have 5 static returns.
    """
    if int(static.sum()) < 100:
        return math.nan
    rng, az = lidar_to_polar(p_L[static])
    key = np.floor(az / az_quantum).astype(np.int64)
    order = np.lexsort((rng, key))  # by azimuth group, then range
    key, rng = key[order], rng[order]
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    counts = np.diff(np.r_[starts, key.size])
    group = np.repeat(np.arange(starts.size), counts)
    mid = starts + (counts - 1) // 2
    dev = np.abs(rng - rng[mid][group])
    mad = dev[np.lexsort((dev, group))][mid]
    ok = counts >= 5
    if int(ok.sum()) < 20:
        return math.nan
    return float(1.4826 * np.median(mad[ok]))


def final_cell_size(
    halves_p_L: list[FloatArray], halves_phi: list[FloatArray], noise: float
) -> float:
    """The smallest cell size of :data:`CELL_SIZES` whose cells average the range noise down to
    :data:`CELL_NOISE_RATIO` of their size (m).

    Mutual nearest neighbours between the two half-turns prefer pairs whose noise cancels their
    misalignment; when a cell's noise (σ/√returns) is comparable to the cell spacing, each outer
    iteration recovers only a few per cent of an ry error, and ry stays biased (docs/algorithms.md).
    The count per cell is the median over the target's cells of both halves.
    """
    if not math.isfinite(noise) or noise <= 0:
        return CELL_SIZES[0]
    for size in CELL_SIZES:
        counts = np.concatenate(
            [_cell_counts(p, ph, size) for p, ph in zip(halves_p_L, halves_phi, strict=True)]
        )
        per_cell = float(np.median(counts)) if counts.size else 1.0
        if noise / math.sqrt(per_cell) <= CELL_NOISE_RATIO * size:
            return size
    return CELL_SIZES[-1]


def _cell_keys(
    p_L: FloatArray, phi: FloatArray, size: float, radius_ref: float
) -> NDArray[np.int64]:
    """(N,) cell index of each return on the sensor grid (platter angle × azimuth)."""
    rng, az = lidar_to_polar(p_L)
    az_step = size / float(np.median(rng))
    phi_step = size / radius_ref
    ia = np.floor(az / az_step).astype(np.int64)
    ip = np.floor(phi / phi_step).astype(np.int64)
    ia -= ia.min()
    ip -= ip.min()
    out: NDArray[np.int64] = ip * (int(ia.max()) + 1) + ia
    return out


def _cell_counts(
    p_L: FloatArray, phi: FloatArray, size: float, radius_ref: float = 0.15
) -> NDArray[np.int64]:
    if p_L.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    _, counts = np.unique(_cell_keys(p_L, phi, size, radius_ref), return_counts=True)
    out: NDArray[np.int64] = counts
    return out


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


def static_mask(
    p_L: FloatArray, *, bin_deg: float = 0.1, range_cell: float = 0.001, fraction: float = 0.6
) -> NDArray[np.bool_]:
    """(N,) True for returns that sit at the same place in L for most of the scan.

    Per azimuth bin of ``bin_deg``, a return is static when at least ``fraction`` of the bin's
    returns lie within ±2.5 ``range_cell`` of it: the platter ring, the background, faces of
    revolution. Independent of H.
    """
    rng, az = lidar_to_polar(p_L)
    if rng.size == 0:
        return np.zeros(0, dtype=bool)
    b = np.floor(az / math.radians(bin_deg)).astype(np.int64)
    b -= b.min()
    c = np.floor(rng / range_cell).astype(np.int64)
    c -= c.min()
    ncell = int(c.max()) + 5
    key = b * ncell + c + 2
    size = (int(b.max()) + 1) * ncell
    if size <= 50_000_000:
        # dense counts: no sort over millions of returns
        counts = np.bincount(key, minlength=size)
        near_all = sum(counts[key + k] for k in (-2, -1, 0, 1, 2))
    else:
        uniq, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
        near = np.zeros_like(cnt)
        for k in (-2, -1, 0, 1, 2):
            pos = np.searchsorted(uniq, uniq + k)
            hit = (pos < uniq.size) & (uniq[np.minimum(pos, uniq.size - 1)] == uniq + k)
            near[hit] += cnt[pos[hit]]
        near_all = near[inv]
    per_bin = np.bincount(b)
    out: NDArray[np.bool_] = near_all >= fraction * np.maximum(per_bin[b], 1)
    return out


def sensor_cells(
    p_L: FloatArray, phi: FloatArray, size: float, *, radius_ref: float = 0.15
) -> tuple[FloatArray, FloatArray]:
    """Average returns over cells of the sensor grid (platter angle × azimuth), ~``size`` m wide.

    Cells are cut in (φ, α), which carry no range noise, so the averages are unbiased (a voxel
    grid in D would select points by their noisy position and pull the averages toward voxel
    centres). A cell spans ``size / radius_ref`` of platter angle and ``size / median range`` of
    azimuth; cells whose ranges spread more than 4·``size`` (a depth edge) are dropped.
    Returns ((C, 3) mean returns in L, (C,) mean φ).
    """
    if p_L.shape[0] == 0:
        return p_L, phi
    rng, _ = lidar_to_polar(p_L)
    key = _cell_keys(p_L, phi, size, radius_ref)
    _, inv, counts = np.unique(key, return_inverse=True, return_counts=True)
    m = counts.size
    mean = np.empty((m, 3))
    for j in range(2):
        mean[:, j] = np.bincount(inv, weights=p_L[:, j], minlength=m) / counts
    mean[:, 2] = np.bincount(inv, weights=p_L[:, 2], minlength=m) / counts
    ph = np.bincount(inv, weights=phi, minlength=m) / counts
    r_mean = np.bincount(inv, weights=rng, minlength=m) / counts
    r_sq = np.bincount(inv, weights=rng * rng, minlength=m) / counts
    spread = np.sqrt(np.maximum(r_sq - r_mean**2, 0.0))
    keep = spread <= max(4.0 * size, 0.004)
    return mean[keep], ph[keep]


def weighted_normals(
    points: FloatArray, k: int, query: NDArray[np.int64] | None = None
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Unit normals and planarity weights from the k nearest points (paper §IV-C).

    ``points`` (N, 3); ``query`` optional indices of the points that need a normal (default
    all). Returns ((Q, 3) unit normals, (Q,) weights, (Q, 3) neighbourhood centroids) with
    ``w = 2(λ2 − λ3)/(λ1 + λ2 + λ3)``, λ1 ≥ λ2 ≥ λ3 the covariance eigenvalues: 1 on a plane,
    0 on an edge or in a blob.
    """
    n = points.shape[0]
    q = np.arange(n) if query is None else np.asarray(query, dtype=np.int64)
    if n < 3 or q.size == 0:
        return np.zeros((q.size, 3)), np.zeros(q.size), np.zeros((q.size, 3))
    k = min(k, n)
    _, idx = cKDTree(points).query(points[q], k=k)
    nb = points[idx]  # (Q, k, 3)
    mean = nb.mean(axis=1)
    cov = np.empty((q.size, 3, 3))
    for a in range(3):
        for b in range(a, 3):
            v = (nb[:, :, a] * nb[:, :, b]).mean(axis=1) - mean[:, a] * mean[:, b]
            cov[:, a, b] = v
            cov[:, b, a] = v
    lam, vec = np.linalg.eigh(cov)  # ascending
    l3, l2, l1 = lam[:, 0], lam[:, 1], lam[:, 2]
    total = np.maximum(l1 + l2 + l3, 1e-30)
    w = np.clip(2.0 * (l2 - l3) / total, 0.0, 1.0)
    return vec[:, :, 0], w, mean


def mutual_neighbours(
    a: FloatArray, b: FloatArray, radius: float
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Index pairs (i, j) of mutual nearest neighbours between (N, 3) a and (M, 3) b within
    ``radius`` metres (KD-tree)."""
    if a.shape[0] == 0 or b.shape[0] == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty.copy()
    da, ia = cKDTree(b).query(a, distance_upper_bound=radius)
    _, ib = cKDTree(a).query(b, distance_upper_bound=radius)
    ok = np.isfinite(da)
    i = np.flatnonzero(ok)
    j = ia[ok]
    mutual = ib[j] == i
    return i[mutual].astype(np.int64), j[mutual].astype(np.int64)


# --- the problem ------------------------------------------------------------------------------
@dataclass
class _Half:
    p_L: FloatArray
    phi: FloatArray


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

    def residuals(self, x: FloatArray) -> FloatArray:
        x6 = self.full(x)
        m = self.m
        d = to_dynamic(m.pa, m.ca, m.sa, x6) - to_dynamic(m.pb, m.cb, m.sb, x6)
        # point of B against A's local plane, and point of A against B's local plane
        ra = np.sqrt(m.wa) * (np.einsum("ij,ij->i", m.na, d) + m.oa)
        rb = np.sqrt(m.wb) * (np.einsum("ij,ij->i", m.nb, d) - m.ob)
        parts = [ra, rb]
        if self.platter is not None and self.platter.shape[0]:
            axis = _rotation(x6)[:, 0]
            parts.append(self.platter_weight * ((self.platter - x6[:3]) @ axis))
        return np.concatenate(parts)


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
    idx = np.sort(rng.choice(half.p_L.shape[0], n, replace=False))
    return _Half(half.p_L[idx], half.phi[idx])


def static_samples(p_static: FloatArray, n: int = 150_000, seed: int = 0) -> FloatArray:
    """A fixed random subset of at most ``n`` static returns, (S, 3) in L.

    Raw returns rather than per-bin averages: grouping by noisy range would bias the averages.
    """
    if p_static.shape[0] <= n:
        return p_static
    rng = np.random.default_rng(seed)
    return p_static[np.sort(rng.choice(p_static.shape[0], n, replace=False))]


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
    t_start = time.perf_counter()
    p_L = np.asarray(p_L, dtype=np.float64)
    phi = np.asarray(phi, dtype=np.float64).reshape(-1)
    if p_L.ndim != 2 or p_L.shape[1] != 3 or p_L.shape[0] != phi.shape[0]:
        raise FineTuningError(
            f"periodicity needs (N, 3) returns and (N,) angles, got {p_L.shape} and {phi.shape}"
        )
    if p_L.shape[0] < 1000:
        raise FineTuningError(
            f"the spin scan has only {p_L.shape[0]} valid returns; periodicity needs a full "
            "revolution of the spin target"
        )
    span = float(np.nanmax(phi) - np.nanmin(phi))
    if span < 2 * math.pi * 0.98:
        raise FineTuningError(
            f"the spin scan covers {math.degrees(span):.0f}° of platter rotation; periodicity "
            "needs one full revolution (360°)"
        )
    # whole revolutions only, so that every half-turn is seen equally often
    revolutions = max(1, math.floor(span / (2 * math.pi) + 0.02))
    keep = phi < np.nanmin(phi) + revolutions * 2 * math.pi
    p_L, phi = p_L[keep], phi[keep]
    timings: dict[str, float] = {}

    t0 = time.perf_counter()
    static, noise = _static_and_noise(p_L)
    p_static_all = static_samples(p_L[static])
    rng = np.random.default_rng(0)
    start6 = start.with_(rx=0.0).as_vector()
    # generous region of interest around the platter under the start H
    q0 = (p_L - start6[:3]) @ _rotation(start6)
    roi = (
        (q0[:, 0] > -0.2)
        & (q0[:, 0] < 0.6)
        & (np.hypot(q0[:, 1], q0[:, 2]) < platter_radius + 0.25)
    )
    phi_w = np.mod(phi, 2 * math.pi)
    half_a = phi_w < math.pi
    p_dyn = p_L[~static]
    halves = [
        _Half(p_L[sel & roi & ~static], phi_w[sel & roi & ~static]) for sel in (half_a, ~half_a)
    ]
    # the last stage keeps the static returns too and drops the platter by the height of its
    # cells: the static test decides per noisy return, and near the target's foot it would keep
    # the returns whose noise moved them off the platter's range (a selection on the noise)
    halves_all = [_Half(p_L[sel & roi], phi_w[sel & roi]) for sel in (half_a, ~half_a)]
    timings["prepare"] = time.perf_counter() - t0
    if min(h.p_L.shape[0] for h in halves) < 500:
        raise FineTuningError(
            f"too few moving returns on the spin target ({halves[0].p_L.shape[0]} and "
            f"{halves[1].p_L.shape[0]} in the two half-turns); is the spin target on the platter?"
        )

    final_voxel = final_cell_size([h.p_L for h in halves], [h.phi for h in halves], noise)
    schedule_ = schedule(settings, final_voxel)[:stages]
    x6 = start6.copy()
    if settings.coarse_to_fine:
        # keep the centroid alignment only where it helps: the view asymmetry of the two
        # half-turns biases the centroids, so a good start can be better than its result
        centred = _centre_halves(halves, x6, settings, np.random.default_rng(1))
        first = schedule_[0]
        cells = [_Half(*sensor_cells(h.p_L, h.phi, first.voxel)) for h in halves]
        if _match(cells, centred, first)[0].pa.shape[0] > _match(cells, x6, first)[0].pa.shape[0]:
            x6 = centred
    history: list[dict[str, Any]] = []
    last: tuple[Any, _Problem] | None = None
    total_outer = 0
    final_cost = math.nan
    for s_i, stage in enumerate(schedule_):
        t_stage = time.perf_counter()
        gauge_ty = settings.gauge == "ty" or not stage.use_platter
        free = [i for i in _free(gauge_ty) if not (stage.hold_ry and i == IDX["ry"])]
        source = halves if stage.hold_ry else halves_all
        stage_halves = [
            _Half(*sensor_cells(h.p_L, h.phi, stage.voxel))
            for h in (_subset(h, stage.max_points, rng) for h in source)
        ]
        for outer in range(stage.max_outer):
            if progress is not None:
                progress(
                    f"periodicity stage {s_i + 1}/{len(schedule_)} ({stage.voxel * 1e3:.0f} mm)",
                    (s_i + outer / stage.max_outer) / len(schedule_),
                )
            matched, n_pts = _match(stage_halves, x6, stage)
            n_matches = matched.pa.shape[0]
            if n_matches < 50:
                raise FineTuningError(
                    f"periodicity stage {s_i + 1}: only {n_matches} matches between the two "
                    f"half-turns (voxel {stage.voxel * 1e3:.0f} mm, radius "
                    f"{stage.match_radius * 1e3:.0f} mm); the start is too far off or the spin "
                    "target is not seen in both half-turns"
                )
            platter = None
            if stage.use_platter:
                platter = _platter_samples(
                    p_static_all, x6, max(0.003, stage.voxel), platter_radius
                )
                if platter.shape[0] < 20:
                    raise FineTuningError(
                        "gauge 'platter': the platter top is not visible in the spin scan "
                        f"({platter.shape[0]} static returns near x_P = 0); use gauge: ty"
                    )
            problem = _Problem(matched, platter, 1.0, free, x6)
            lo, hi = _bounds(x6, start6, free, settings)
            res = least_squares(
                problem.residuals,
                x6[free],
                bounds=(lo, hi),
                method="trf",
                x_scale=np.full(len(free), 1e-3),
                xtol=settings.xtol,
                ftol=settings.ftol,
                max_nfev=settings.max_nfev,
            )
            new6 = problem.full(res.x)
            step = np.abs(new6 - x6)
            x6 = new6
            total_outer += 1
            final_cost = float(np.mean(res.fun**2))
            last = (res, problem)
            history.append(
                {
                    "stage": s_i + 1,
                    "voxel_m": stage.voxel,
                    "points": n_pts,
                    "matches": int(n_matches),
                    "platter_samples": 0 if platter is None else int(platter.shape[0]),
                    "cost": final_cost,
                    "nfev": int(res.nfev),
                }
            )
            if _converged(history, outer, step, stage):
                break
        timings[f"stage{s_i + 1}"] = time.perf_counter() - t_stage

    assert last is not None
    res, problem = last
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
            "static_returns": int(static.sum()),
            "range_noise_m": noise,
            "sigma_independent": sigma_independent,
            "sigma_blocks": sigma_blocks,
            "sigma_noise_inflation": inflation,
            "covariance": covariance_record(reported_cov, problem.free),
            "final_cell_m": final_voxel,
            "moving_returns": int(p_dyn.shape[0]),
            "ry_at_bound": bool(at_bound),
            "ry_bound_rad": [ry_lo, ry_hi],
            "rms_m": math.sqrt(final_cost),
        },
    )


def _static_and_noise(p_L: FloatArray) -> tuple[NDArray[np.bool_], float]:
    """The static returns and the range noise σ (m) of a spin scan.

    The static test's range window must be wider than the noise, or a noisy platter ring is not
    found static and its σ is underestimated: a first pass with 1 mm cells estimates σ, a second
    uses cells of 1.5 σ (at least 1 mm).
    """
    static = static_mask(p_L)
    noise = range_noise(p_L, static)
    if math.isfinite(noise) and 1.5 * noise > 0.001:
        noise = range_noise(p_L, static_mask(p_L, range_cell=1.5 * noise))
    return static, noise


def _converged(
    history: list[dict[str, Any]], outer: int, step: FloatArray, stage: Stage
) -> bool:
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


def _match(halves: list[_Half], x6: FloatArray, stage: Stage) -> tuple[_Matched, int]:
    """Map both half-turns' cells to D under H, drop the platter, match, compute normals."""
    mapped: list[tuple[FloatArray, FloatArray, FloatArray, FloatArray]] = []
    n_pts = 0
    for h in halves:
        c, s = np.cos(h.phi), np.sin(h.phi)
        d = to_dynamic(h.p_L, c, s, x6)
        if stage.platter_drop is not None:
            keep = d[:, 0] > stage.platter_drop
            d, pl, c, s = d[keep], h.p_L[keep], c[keep], s[keep]
        else:
            pl = h.p_L
        mapped.append((d, pl, c, s))
        n_pts += d.shape[0]
    (da, pa, ca, sa), (db, pb, cb, sb) = mapped
    i, j = mutual_neighbours(da, db, stage.match_radius)
    na, wa, ma = weighted_normals(da, stage.normal_neighbours, i)
    nb, wb, mb = weighted_normals(db, stage.normal_neighbours, j)
    # each residual measures a point against the other half's local plane fit (through its
    # neighbourhood centroid), not against one noisy point; the offset moves with the point
    oa = np.einsum("ij,ij->i", na, ma - da[i])
    ob = np.einsum("ij,ij->i", nb, mb - db[j])
    block = block_ids(da[i], SIGMA_BLOCK)
    matched = _Matched(pa[i], ca[i], sa[i], pb[j], cb[j], sb[j], na, nb, wa, wb, oa, ob, block)
    return matched, n_pts


SIGMA_BLOCK = 0.02
"""Edge (m) of the spatial blocks whose residuals are taken as correlated in the covariance."""


def block_ids(points: FloatArray, size: float) -> NDArray[np.int64]:
    """(N,) a dense block index for (N, 3) points on a grid of ``size`` m."""
    if points.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    cells = np.floor(points / size).astype(np.int64)
    _, inv = np.unique(cells, axis=0, return_inverse=True)
    out: NDArray[np.int64] = inv.reshape(-1).astype(np.int64)
    return out


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
    recording: Recording,
    start: Extrinsics,
    settings: PeriodicitySettings = PeriodicitySettings(),
    *,
    platter_radius: float = DEFAULT_PLATTER_RADIUS,
    progress: Progress | None = None,
) -> CalibrationResult:
    """Periodicity fine-tuning on a spin-scan :class:`~calstation.recording.Recording`."""
    p_L, phi = recording.points_lidar()
    try:
        return periodicity_fine_tune_points(
            p_L, phi, start, settings, platter_radius=platter_radius, progress=progress
        )
    except FineTuningError as exc:
        raise FineTuningError(f"{recording.path}: {exc}") from None
