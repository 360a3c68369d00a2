"""A spin scan made ready for fine-tuning: returns in L with their platter angles, their polar
coordinates, the static returns and the range noise.

This is the per-scan work of the fine-tuning, done once: the periodicity stages and the shape
passes reuse it. :class:`SpinScanBuilder` does the per-line part as the lines arrive (in the
station and in ``calstation run``), so that only the whole-scan part is left when the scan
ends (docs/performance.md).
"""

from __future__ import annotations

import bisect
import math
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Generic, Protocol, TypeVar

import numpy as np
from numpy.typing import NDArray

from calstation.engine.frames import FloatArray, lidar_to_polar

if TYPE_CHECKING:
    from calstation.engine.scan import Scan


class LineLike(Protocol):
    """What :class:`SpinScanBuilder` reads of a lidar line (a driver's
    :class:`calstation.drivers.LidarLine` is one): (n,) arrays and each return's time."""

    @property
    def azimuth_rad(self) -> NDArray[np.float64]: ...
    @property
    def range_m(self) -> NDArray[np.float64]: ...
    @property
    def valid(self) -> NDArray[np.bool_]: ...

    def point_times_ns(self) -> NDArray[np.int64]: ...


class EncoderReading(Protocol):
    """An encoder reading (a driver's :class:`calstation.drivers.EncoderSample` is one)."""

    @property
    def timestamp_ns(self) -> int: ...
    @property
    def count(self) -> int: ...


STATIC_BIN_DEG = 0.1
"""Azimuth bin of the static test (degrees)."""

DENSE_LIMIT = 20_000_000
"""Largest (azimuth bin × range cell) grid counted densely (int64 counts: 160 MB)."""

NOISE_SAMPLE = 300_000
"""Returns used to estimate the range noise (a regular subset of the scan)."""


def static_mask(
    p_L: FloatArray | None = None,
    *,
    polar: tuple[FloatArray, FloatArray] | None = None,
    bin_deg: float = STATIC_BIN_DEG,
    range_cell: float = 0.001,
    fraction: float = 0.6,
) -> NDArray[np.bool_]:
    """(N,) True for returns that sit at the same place in L for most of the scan.

    Per azimuth bin of ``bin_deg``, a return is static when at least ``fraction`` of the bin's
    returns lie within ±2.5 ``range_cell`` of it: the platter ring, the background, faces of
    revolution. Independent of H. Give the returns as (N, 3) ``p_L`` or as ``polar`` (range,
    azimuth) arrays.
    """
    if polar is None:
        if p_L is None:
            raise ValueError("static_mask needs the returns as p_L or as polar")
        polar = lidar_to_polar(p_L)
    rng, az = polar
    return static_of_cells(*static_cells(rng, az, bin_deg, range_cell), fraction=fraction)


def static_cells(
    rng: FloatArray, az: FloatArray, bin_deg: float = STATIC_BIN_DEG, range_cell: float = 0.001
) -> tuple[NDArray[np.int32], NDArray[np.int32]]:
    """The static test's (azimuth bin, range cell) of each return, (N,) each; a line's can be
    found as it arrives."""
    b = np.floor(az / math.radians(bin_deg)).astype(np.int32)
    c = np.floor(rng / range_cell).astype(np.int32)
    return b, c


def static_of_cells(
    b: NDArray[np.int32], c: NDArray[np.int32], fraction: float = 0.6
) -> NDArray[np.bool_]:
    """:func:`static_mask` from the returns' azimuth bins and range cells (:func:`static_cells`)."""
    if b.size == 0:
        return np.zeros(0, dtype=bool)
    bmin, cmin = int(b.min()), int(c.min())
    # two empty cells either side of each bin's range cells keep the windows inside the bin
    ncell = int(c.max()) - cmin + 5
    nbin = int(b.max()) - bmin + 1
    size = nbin * ncell
    if size > DENSE_LIMIT:
        return _static_of_sparse_cells(b.astype(np.int64) - bmin, c - cmin, ncell, fraction)
    # int32 when the cells and the counts fit: half the memory to write and gather from
    key: NDArray[np.signedinteger[Any]] = b.astype(np.int32 if size + 8 < 2**31 else np.int64)
    key -= bmin
    key *= ncell
    key += c
    key += 2 - cmin
    # each cell's count in the window cell − 2 … cell + 2 from a running sum (no sort of the
    # returns), judged once per cell; each return then reads its cell's verdict
    running: NDArray[np.signedinteger[Any]] = np.zeros(
        size + 5, dtype=np.int32 if b.size < 2**31 else np.int64)
    np.cumsum(np.bincount(key, minlength=size), out=running[3 : size + 3])
    running[size + 3 :] = running[size + 2]
    per_bin = np.diff(running[2 : size + 3 : ncell])  # running[2 + j·ncell]: before bin j
    window = (running[5:] - running[:-5]).reshape(nbin, ncell)
    static_cell = window >= fraction * np.maximum(per_bin, 1)[:, None]
    out: NDArray[np.bool_] = static_cell.reshape(-1)[key]
    return out


def _static_of_sparse_cells(
    b: NDArray[np.int64], c: NDArray[np.int32], ncell: int, fraction: float
) -> NDArray[np.bool_]:
    """:func:`static_of_cells` for a grid too large to count densely: the occupied cells
    sorted, each window's count found by search (``b``, ``c`` from 0)."""
    key = b * ncell
    key += c
    key += 2
    uniq, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
    near_u = np.zeros_like(cnt)
    for k in (-2, -1, 0, 1, 2):
        pos = np.searchsorted(uniq, uniq + k)
        hit = (pos < uniq.size) & (uniq[np.minimum(pos, uniq.size - 1)] == uniq + k)
        near_u[hit] += cnt[pos[hit]]
    near = near_u[inv]
    per_bin = np.bincount(b)
    out: NDArray[np.bool_] = near >= fraction * np.maximum(per_bin[b], 1)
    return out


def range_noise(
    p_L: FloatArray | None,
    static: NDArray[np.bool_],
    *,
    polar: tuple[FloatArray, FloatArray] | None = None,
    az_quantum: float = 1e-4,
) -> float:
    """Range noise σ (m) of the lidar, from the static returns of one scan.

    Static returns (the platter ring, the background) come back at the same range for the same
    azimuth whatever the platter angle, so their spread per azimuth is the range noise. Azimuths
    are grouped in ``az_quantum`` rad (0.1 mm across at 1 m); the σ is 1.4826 × the median of the
    per-azimuth median absolute deviations (robust to mixed pixels). NaN when fewer than 20
    azimuths have 5 static returns.
    """
    if int(static.sum()) < 100:
        return math.nan
    if polar is None:
        assert p_L is not None
        rng, az = lidar_to_polar(p_L[static])
    else:
        rng, az = polar[0][static], polar[1][static]
    key = np.floor(az / az_quantum).astype(np.int64)
    key -= key.min()
    rng = rng[_by_group_then_value(key, rng)]
    key = np.sort(key)
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    counts = np.diff(np.r_[starts, key.size])
    group = np.repeat(np.arange(starts.size), counts)
    mid = starts + (counts - 1) // 2
    dev = np.abs(rng - rng[mid][group])
    mad = dev[_by_group_then_value(group, dev)][mid]
    ok = counts >= 5
    if int(ok.sum()) < 20:
        return math.nan
    return float(1.4826 * np.median(mad[ok]))


def _by_group_then_value(group: NDArray[np.int64], value: FloatArray) -> NDArray[np.intp]:
    """The order by ``group`` (≥ 0), then by ``value``: one sort of ``group·2^k + value`` with
    2^k above the values' span (as ``numpy.lexsort``, 6× quicker; values closer than ~1 nm in
    one group may come in either order)."""
    v = value - value.min()
    scale = 2.0 ** math.ceil(math.log2(float(v.max()) + 1.0))
    out: NDArray[np.intp] = np.argsort(group * scale + v)
    return out


def static_and_noise(
    rng: FloatArray,
    az: FloatArray,
    cells: tuple[NDArray[np.int32], NDArray[np.int32]] | None = None,
) -> tuple[NDArray[np.bool_], float]:
    """The static returns (1 mm range cells) and the range noise σ (m) of a spin scan.

    The static test's range window must be wider than the noise, or a noisy platter ring is not
    found static and its σ is underestimated: a first pass with 1 mm cells estimates σ, a second
    uses cells of 1.5 σ (at least 1 mm). The σ comes from a regular subset of
    :data:`NOISE_SAMPLE` returns (every azimuth keeps its share; the static test is a fraction,
    so it is unchanged by the subset). ``cells``: the returns' :func:`static_cells`, when
    already found (line by line, while scanning).
    """
    from calstation.engine.neighbours import pair

    step = max(1, math.ceil(rng.size / NOISE_SAMPLE))
    sub = (np.ascontiguousarray(rng[::step]), np.ascontiguousarray(az[::step]))

    def noise_of_subset() -> float:
        noise = range_noise(None, static_mask(polar=sub), polar=sub)
        if math.isfinite(noise) and 1.5 * noise > 0.001:
            noise = range_noise(None, static_mask(polar=sub, range_cell=1.5 * noise), polar=sub)
        return noise

    # the whole scan's static test and the noise (on its subset) side by side, on two cores
    static, noise = pair(
        lambda which: (
            static_of_cells(*(static_cells(rng, az) if cells is None else cells))
            if which == "static"
            else noise_of_subset()
        ),
        ("static",),
        ("noise",),
    )
    assert isinstance(static, np.ndarray) and isinstance(noise, float)
    return static, noise


@dataclass
class SpinScan:
    """A spin scan ready for fine-tuning (all arrays share the order of the returns).

    The static returns and the range noise are found on first use (the cube check needs only
    the returns) and kept.
    """

    p_L: FloatArray
    """(N, 3) valid returns in L (m)"""
    phi: FloatArray
    """(N,) platter angles (rad, unwrapped)"""
    rng: FloatArray
    """(N,) ranges (m)"""
    az: FloatArray
    """(N,) azimuths (rad)"""
    timings: dict[str, float] = field(default_factory=dict)
    """seconds spent preparing, by step"""
    cells: tuple[NDArray[np.int32], NDArray[np.int32]] | None = field(default=None, repr=False)
    """the static test's cells of the returns (:func:`static_cells`), when found while scanning"""
    memo: dict[str, object] = field(default_factory=dict, repr=False)
    """results derived from the returns that later steps may reuse (the cube check's
    segmentation under the last H: :func:`calstation.engine.cube.check_cube_points`)"""
    _static: NDArray[np.bool_] | None = field(default=None, repr=False)
    _noise: float = math.nan

    @property
    def n_points(self) -> int:
        return int(self.phi.shape[0])

    @property
    def static(self) -> NDArray[np.bool_]:
        """(N,) returns that stay put over the scan (:func:`static_mask`)."""
        return self._static_and_noise()[0]

    @property
    def noise(self) -> float:
        """Range noise σ (m); NaN when the scan has too few static returns."""
        return self._static_and_noise()[1]

    def _static_and_noise(self) -> tuple[NDArray[np.bool_], float]:
        if self._static is None:
            t0 = time.perf_counter()
            if self.rng.size:
                self._static, self._noise = static_and_noise(self.rng, self.az, self.cells)
                self.cells = None
            else:
                self._static, self._noise = np.zeros(0, dtype=bool), math.nan
            self.timings["static"] = time.perf_counter() - t0
        return self._static, self._noise


def prepare(
    p_L: FloatArray,
    phi: FloatArray,
    polar: tuple[FloatArray, FloatArray] | None = None,
) -> SpinScan:
    """:class:`SpinScan` from (N, 3) returns in L and their (N,) platter angles; ``polar``: the
    returns' (range, azimuth) as measured, when known (else computed from ``p_L``)."""
    t0 = time.perf_counter()
    p_L = np.asarray(p_L, dtype=np.float64)
    phi = np.asarray(phi, dtype=np.float64).reshape(-1)
    if polar is None:
        polar = lidar_to_polar(p_L) if p_L.shape[0] else (np.zeros(0), np.zeros(0))
    rng, az = polar
    return SpinScan(p_L, phi, rng, az, {"polar": time.perf_counter() - t0})


def prepared_or_read(recording: Scan | None, prepared: SpinScan | None) -> SpinScan:
    """``prepared``, the returns of ``recording`` already prepared, else :func:`from_recording`
    of ``recording`` (a cube scan still being taken has only the former)."""
    if prepared is not None:
        return prepared
    if recording is None:
        raise ValueError("the scan's recording or its prepared returns are needed")
    return from_recording(recording)


def from_recording(recording: Scan) -> SpinScan:
    """:class:`SpinScan` of a recording's valid returns with a known platter angle, prepared
    anew at each call: whoever fine-tunes one scan several times (the calibration pipeline's
    stages, the bench's perturbed starts) prepares it once and hands the result on, and a scan
    prepared while it was taken is :meth:`SpinScanBuilder.finish`'s (the engine keeps none)."""
    t0 = time.perf_counter()
    p_L, phi, rng, az = recording.valid_returns()
    t1 = time.perf_counter()
    scan = prepare(p_L, phi, (rng, az))
    scan.timings["points"] = t1 - t0
    return scan


S = TypeVar("S", bound=np.generic)


class _Rows(Generic[S]):
    """A growing array: rows appended as they arrive, the filled part handed out as a view, so
    that nothing is concatenated when the scan ends."""

    def __init__(self, dtype: type[S], width: int | None = None, capacity: int = 1 << 16) -> None:
        self.width = width
        self.data: NDArray[S] = np.empty(self._shape(capacity), dtype)
        self.n = 0

    def _shape(self, rows: int) -> tuple[int, ...]:
        return (rows,) if self.width is None else (rows, self.width)

    def reserve(self, m: int) -> slice:
        """Room for ``m`` more rows (growing by half when full); their slice."""
        if self.n + m > self.data.shape[0]:
            grown = np.empty(self._shape(max(self.n + m, self.data.shape[0] * 3 // 2)),
                             self.data.dtype)
            grown[: self.n] = self.data[: self.n]
            self.data = grown
        rows = slice(self.n, self.n + m)
        self.n += m
        return rows

    def append(self, values: NDArray[S]) -> None:
        rows = self.reserve(values.shape[0])  # may replace self.data
        self.data[rows] = values

    def view(self) -> NDArray[S]:
        return self.data[: self.n]


class SpinScanBuilder:
    """Prepares a spin scan while its lines arrive.

    Fed beside the recording writer (the same ``write_line`` / ``write_encoder`` /
    ``write_turntable`` calls), it appends each line's valid returns, converted to L and
    stamped with their times, to growing arrays as the line arrives, and gives them their
    platter angles as soon as encoder readings on both sides of the line have arrived.
    :meth:`finish` is left with the last lines' angles (the static returns and the range noise
    are found when first used); the arrays are handed over as they are. The result is the
    :class:`SpinScan` that :func:`prepare` makes from the recording's points: an angle
    interpolated between two readings does not depend on the readings that come later.
    """

    def __init__(
        self, counts_per_revolution: int, encoder_direction: int, encoder_latency_s: float
    ) -> None:
        self.counts_per_revolution = counts_per_revolution
        self.encoder_direction = encoder_direction
        self.encoder_latency_s = encoder_latency_s
        self._latency_ns = round(encoder_latency_s * 1e9)
        self._t = _Rows(np.int64)
        self._p = _Rows(np.float64, 3)
        self._rng = _Rows(np.float64)
        self._az = _Rows(np.float64)
        self._bin = _Rows(np.int32)
        self._cell = _Rows(np.int32)
        self._phi = _Rows(np.float64)
        """angles of the first ``_phi.n`` returns, found while scanning"""
        self._line_ends: list[int] = []
        """row after each line's last return"""
        self._lines_with_angles = 0
        self._enc_t: list[int] = []
        self._enc_c: list[int] = []
        self._late = False
        """a reading arrived after a newer one: the angles so far are to be found again"""
        self._moved = False
        """the readings so far hold two counts (before, every angle would be one constant)"""
        self._enc_arrays: tuple[NDArray[np.int64], NDArray[np.int64]] | None = None
        self.during_s = 0.0
        """seconds of per-line work done while the scan ran"""
        self._done: SpinScan | None = None
        self._handed: dict[int, SpinScan] = {}
        """the scans :meth:`so_far` handed out, by their lines: :meth:`first_lines` gives the same
        object back, so what a fit made while scanning kept in its ``memo`` reaches the step
        after the scan"""

    def write_line(self, line: LineLike) -> None:
        t0 = time.perf_counter()
        valid = np.asarray(line.valid, dtype=bool)
        rng = np.asarray(line.range_m, dtype=np.float64)[valid]
        az = np.asarray(line.azimuth_rad, dtype=np.float64)[valid]
        rows = self._p.reserve(rng.size)  # may replace self._p.data
        p = self._p.data[rows]  # a view of the new rows
        np.multiply(rng, np.sin(az), out=p[:, 0])
        np.multiply(rng, np.cos(az), out=p[:, 1])
        p[:, 2] = 0.0
        self._t.append(line.point_times_ns()[valid])
        self._rng.append(rng)
        self._az.append(az)
        b, c = static_cells(rng, az)
        self._bin.append(b)
        self._cell.append(c)
        self._line_ends.append(self._t.n)
        self._angles_so_far()
        self.during_s += time.perf_counter() - t0

    def write_encoder(self, samples: Iterable[EncoderReading]) -> None:
        t0 = time.perf_counter()
        for sample in samples:
            t, count = int(sample.timestamp_ns), int(sample.count)
            if self._enc_t and t < self._enc_t[-1]:
                # a reading that arrives after a newer one (a driver's queue handing one over
                # late) goes in its place; the angles found so far are found again with it
                i = bisect.bisect_right(self._enc_t, t)
                self._enc_t.insert(i, t)
                self._enc_c.insert(i, count)
                self._late = True
            else:
                self._enc_t.append(t)
                self._enc_c.append(count)
            self._moved = self._moved or count != self._enc_c[0] or count != self._enc_c[-1]
        self._angles_so_far()
        self.during_s += time.perf_counter() - t0

    def write_turntable(self, status: object) -> None:
        """Turntable states carry nothing the fine-tuning needs."""

    def _angles_so_far(self) -> None:
        """Angles of the waiting lines that lie between the first and the last reading."""
        n_lines = len(self._line_ends)
        if not self._moved:
            # readings of one count give every time that count's angle, even outside their
            # span: wait for the platter to move, as the whole recording is prepared with it
            return
        if self._late:
            self._angles_again()
        if self._lines_with_angles == n_lines:
            return
        # a line waits until a reading follows its last return; returns before the first
        # reading have no angle (NaN: dropped), as when the whole recording is prepared
        hi = self._enc_t[-1] - self._latency_ns
        t = self._t.data
        ready = self._lines_with_angles
        while ready < n_lines:
            first = self._line_ends[ready - 1] if ready else 0
            last = self._line_ends[ready]
            if last > first and int(t[last - 1]) > hi:
                break
            ready += 1
        if ready == self._lines_with_angles:
            return
        end = self._line_ends[ready - 1]
        self._phi.append(self._angle(t[self._phi.n : end], *self._encoder_arrays()))
        self._lines_with_angles = ready

    def _encoder_arrays(self) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        if self._enc_arrays is None or self._enc_arrays[0].size != len(self._enc_t):
            self._enc_arrays = (
                np.asarray(self._enc_t, dtype=np.int64),
                np.asarray(self._enc_c, dtype=np.int64),
            )
        return self._enc_arrays

    def _angles_again(self) -> None:
        """After a late reading: the angles of the lines that have them, from every reading
        (into new rows: a fit under way keeps the view it was handed)."""
        self._late = False
        self._enc_arrays = None
        self._handed.clear()  # their angles were found without this reading
        phi = _Rows(np.float64, capacity=max(self._phi.data.shape[0], 1))
        if self._phi.n:
            phi.append(self._angle(self._t.data[: self._phi.n], *self._encoder_arrays()))
        self._phi = phi

    def _angle(
        self, t: NDArray[np.int64], enc_t: NDArray[np.int64], enc_c: NDArray[np.int64]
    ) -> FloatArray:
        from calstation.engine.scan import encoder_angle

        return encoder_angle(
            t,
            enc_t,
            enc_c,
            self.counts_per_revolution,
            self.encoder_direction,
            self.encoder_latency_s,
        )

    @property
    def lines_ready(self) -> int:
        """How many lines, from the first, :meth:`so_far` holds."""
        return self._lines_with_angles

    def so_far(self) -> SpinScan | None:
        """The lines prepared so far whose platter angles are known, as a :class:`SpinScan`
        (None before any): a view of the growing arrays, which later lines do not change, so
        the scan goes on while it is fine-tuned (a reading handed over after a newer one puts
        the angles in new arrays)."""
        if self._done is not None:
            return self._done
        lines = self._lines_with_angles
        if lines == 0:
            return None
        end = self._line_ends[lines - 1]
        phi = self._phi.view()[:end]
        p_L, rng, az = self._p.view()[:end], self._rng.view()[:end], self._az.view()[:end]
        b, c = self._bin.view()[:end], self._cell.view()[:end]
        keep = np.isfinite(phi)
        if not keep.all():
            phi, p_L, rng, az, b, c = phi[keep], p_L[keep], rng[keep], az[keep], b[keep], c[keep]
        scan = SpinScan(p_L, phi, rng, az, {"during_scan": self.during_s}, cells=(b, c))
        self._handed[lines] = scan
        return scan

    @property
    def lines(self) -> int:
        """How many lines the builder was handed."""
        return len(self._line_ends)

    def first_lines(self, lines: int) -> SpinScan:
        """The first ``lines`` lines of the finished scan, prepared: the :class:`SpinScan` that
        :func:`prepare` makes of the recording cut after them
        (:meth:`calstation.engine.scan.Scan.first_lines`), without preparing it again. The
        whole scan (:meth:`finish`) when it has no more lines."""
        done = self.finish()
        if lines >= len(self._line_ends):
            return done
        if lines in self._handed:
            return self._handed[lines]
        end = self._line_ends[lines - 1] if lines > 0 else 0
        phi, p_L = self._phi.view()[:end], self._p.view()[:end]
        rng, az = self._rng.view()[:end], self._az.view()[:end]
        b, c = self._bin.view()[:end], self._cell.view()[:end]
        keep = np.isfinite(phi)
        if not keep.all():
            phi, p_L, rng, az, b, c = phi[keep], p_L[keep], rng[keep], az[keep], b[keep], c[keep]
        return SpinScan(p_L, phi, rng, az, {"during_scan": self.during_s}, cells=(b, c))

    def finish(self) -> SpinScan:
        """The prepared scan (computed once; later calls return the same object)."""
        if self._done is not None:
            return self._done
        from calstation.errors import RecordingError

        t0 = time.perf_counter()
        if not self._enc_t:
            raise RecordingError(
                "the spin scan has no encoder readings: the platter angle is unknown"
            )
        if self._late:
            self._angles_again()
        t = self._t.view()
        if self._phi.n < t.shape[0]:
            self._phi.append(self._angle(t[self._phi.n :], *self._encoder_arrays()))
        phi, p_L, rng, az = self._phi.view(), self._p.view(), self._rng.view(), self._az.view()
        b, c = self._bin.view(), self._cell.view()
        keep = np.isfinite(phi)
        if not keep.all():
            phi, p_L, rng, az, b, c = phi[keep], p_L[keep], rng[keep], az[keep], b[keep], c[keep]
        self._t = _Rows(np.int64, capacity=0)
        self._done = SpinScan(
            p_L,
            phi,
            rng,
            az,
            {"during_scan": self.during_s, "points": time.perf_counter() - t0},
            cells=(b, c),
        )
        return self._done
