"""The spin scan's returns as the periodicity fine-tuning uses them: the two half-turns, their
random subsets, and cells of the sensor grid (platter angle × azimuth) that average them.

Names with a leading underscore are shared by the modules of this package only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from calstation.engine.blocks import positions
from calstation.engine.frames import FloatArray, euler_to_matrix, lidar_to_polar
from calstation.engine.rangemodel import correct_vector
from calstation.engine.spinscan import SpinScan
from calstation.errors import FineTuningError


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
    """(N, 3) points in L with their platter angles (as cos, sin) → (N, 3) in D, for H = x6
    (and the range model after H in it, :mod:`calstation.engine.rangemodel`)."""
    q = (correct_vector(p_L, x6) - x6[:3]) @ _rotation(x6)
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


# --- the half-turns ---------------------------------------------------------------------------
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

    def subset(self, n: int | None, rng: np.random.Generator) -> _Half:
        """A random subset of at most ``n`` of the half-turn's returns, in their order (None:
        all)."""
        pick = _draw(self.p_L.shape[0], n, rng)
        return self if pick is None else self.take(pick)


def _draw(size: int, n: int | None, rng: np.random.Generator) -> NDArray[np.int64] | None:
    """Sorted random indices of at most ``n`` of ``size`` items (None: all of them)."""
    if n is None or size <= n:
        return None
    return np.sort(rng.choice(size, n, replace=False))


def _gather(scan: SpinScan, j: NDArray[np.int64]) -> _Half:
    """The scan's returns ``j`` as a half-turn (their platter angles wrapped to [0, 2π))."""
    return _Half(scan.p_L[j], np.mod(scan.phi[j], 2 * math.pi), scan.rng[j], scan.az[j])


@dataclass(frozen=True)
class _Gathered:
    """One half-turn's returns as indices into the scan, gathered into a :class:`_Half` when a
    stage needs them: the half-turns of every return (the last stage's) held as copies through
    the whole fine-tuning were 120 MB of the station's peak memory on a 2-turn scan."""

    scan: SpinScan
    idx: NDArray[np.int64]

    def subset(self, n: int | None, rng: np.random.Generator) -> _Half:
        """:meth:`_Half.subset` of the gathered half (the same returns, drawn alike)."""
        pick = _draw(self.idx.shape[0], n, rng)
        return _gather(self.scan, self.idx if pick is None else self.idx[pick])


def static_samples(static: NDArray[np.int64], n: int = 150_000, seed: int = 0) -> NDArray[np.int64]:
    """A fixed random subset of at most ``n`` of the indices ``static`` of static returns.

    Raw returns rather than per-bin averages: grouping by noisy range would bias the averages.
    """
    pick = _draw(static.shape[0], n, np.random.default_rng(seed))
    return static if pick is None else static[pick]


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


def _near_platter(
    p_L: FloatArray, keep: NDArray[np.bool_], start6: FloatArray, radius: float
) -> NDArray[np.intp]:
    """Indices of the kept returns from 0.2 m below to 0.6 m above the platter and within
    ``radius`` of the axis under ``start6``, tested a block at a time
    (:mod:`calstation.engine.blocks`): the whole scan's coordinates at once were 170 MB of
    temporaries, the station's peak memory."""
    R = _rotation(start6)
    t_P = start6[:3] @ R

    def block(rows: slice) -> NDArray[np.intp]:
        xy = p_L[rows, :2]  # the returns lie in the scan plane (z_L = 0)
        # x_P first, then the radius on what is left
        x_P = xy @ R[:2, 0] - t_P[0]
        j = np.flatnonzero(keep[rows] & (x_P > -0.2) & (x_P < 0.6))
        yz = xy[j] @ R[:2, 1:] - t_P[1:]
        out: NDArray[np.intp] = j[np.hypot(yz[:, 0], yz[:, 1]) < radius]
        return out

    return positions(block, p_L.shape[0])


def _split(
    scan: SpinScan, keep: NDArray[np.bool_], start6: FloatArray, platter_radius: float
) -> tuple[list[_Half], list[_Gathered], FloatArray]:
    """The two half-turns of the moving returns, the two half-turns of all returns (gathered
    when the last stage needs them), and a subset of the static returns, within a generous
    region around the platter under the start.

    The last stage keeps the static returns too and drops the platter by the height of its
    cells: the static test decides per noisy return, and near the target's foot it would keep
    the returns whose noise moved them off the platter's range (a selection on the noise).
    """
    idx = _near_platter(scan.p_L, keep, start6, platter_radius + 0.25)
    phi_w = np.mod(scan.phi[idx], 2 * math.pi)
    first = phi_w < math.pi
    moving = ~scan.static[idx]
    halves_all = [_Gathered(scan, idx[first]), _Gathered(scan, idx[~first])]
    halves = [_gather(scan, idx[first & moving]), _gather(scan, idx[~first & moving])]
    static_idx = np.flatnonzero(keep & scan.static)
    p_static = scan.p_L[static_samples(static_idx)]
    if min(h.p_L.shape[0] for h in halves) < 500:
        raise FineTuningError(
            f"too few moving returns on the spin target ({halves[0].p_L.shape[0]} and "
            f"{halves[1].p_L.shape[0]} in the two half-turns); is the spin target on the platter?"
        )
    return halves, halves_all, p_static
