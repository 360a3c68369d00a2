"""Which of a cube scan's returns are the QA cube's faces and the platter top, chosen by casting
each return's ray against the model — an upright cube of the recipe's edge standing on the
platter, under an estimate of H and the lidar's range model — not by where the noisy ranges
put them (the known-size fit, :mod:`calstation.engine.cubefit`; docs/algorithms.md)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from calstation.engine.blocks import by_blocks, positions, stacked
from calstation.engine.frames import PARAMETER_NAMES, Extrinsics, FloatArray
from calstation.engine.rangemodel import RangeModel, unit_rays
from calstation.engine.spinscan import SpinScan
from calstation.errors import FineTuningError

FIT_POINTS = 200_000
"""Labelled returns the fit uses at most (a fixed random subset, :func:`_kept`): 4 turns at
1000 lines/s."""
MIN_FACES = 3
"""Side faces and top together the fit needs: two adjacent sides fix both directions across
the axis; a third face ties the cube's centre."""

PLATTER_POINTS = 60_000
"""Platter returns the fit with a range model uses at most (a fixed random subset,
:func:`_kept`)."""


@dataclass(frozen=True)
class _Faces:
    """The labelled returns of one round and the cube's pose they were labelled against."""

    p_L: FloatArray
    """(N, 3) returns in L"""
    cos: FloatArray
    """(N,) cosine of each return's platter angle"""
    sin: FloatArray
    """(N,) sine of each return's platter angle"""
    rays: FloatArray
    """(N, 3) unit rays in L"""
    side: NDArray[np.bool_]
    """(N,) on a side face (else on the top)"""
    across_u: NDArray[np.bool_]
    """(N,) a side face whose normal is the box's first horizontal axis (else its second)"""
    sign: FloatArray
    """(N,) +1 on the face at the axis's positive end, −1 at its negative end"""
    pose: FloatArray
    """(4,) the box's centre (y, z in D), yaw (rad) and top height (x in D) under the start"""
    noise: float
    """range noise (m) on the faces"""
    faces: int
    """faces labelled"""


def _spun(q: FloatArray, cos: FloatArray, sin: FloatArray) -> FloatArray:
    """(N, 3) vectors in P taken into D: Rx(φ)ᵀ·q (φ as its cosine and sine)."""
    return np.column_stack([q[:, 0], cos * q[:, 1] + sin * q[:, 2],
                            -sin * q[:, 1] + cos * q[:, 2]])


def _turned(v: FloatArray, H: Extrinsics, cos: FloatArray, sin: FloatArray) -> FloatArray:
    """(N, 3) vectors in L taken into D: Rx(φ)ᵀ·Rᵀ·v (φ as its cosine and sine)."""
    return _spun(v @ H.R, cos, sin)


MARGIN = 0.006
"""How far (m) from a face's edges, and from the cube's footprint on the platter, a return's
ray must meet its surface to be used: the beam's footprint and the mixed pixels of an edge
stay out."""


def _near_platter(scan: SpinScan, v: FloatArray, radius: float) -> NDArray[np.intp]:
    """The returns whose ray meets the platter's top plane inside its rim (under the estimate
    ``v``), or something above it: those :func:`model_labels` may use (the background stays
    out). Chosen by the ray alone, a block of returns at a time
    (:mod:`calstation.engine.blocks`)."""
    H = Extrinsics.from_vector(v[: len(PARAMETER_NAMES)])
    origin = -(H.t @ H.R)

    def block(rows: slice) -> NDArray[np.intp]:
        p_L = scan.p_L[rows]
        # first on the returns as they are (the ray's length does not move where it meets the
        # plane): the few within a millimetre of the rim, or inside, are tested on their unit
        # rays
        q = p_L @ H.R  # in P
        with np.errstate(divide="ignore", invalid="ignore"):
            s_hit = -origin[0] / q[:, 0]
            y = origin[1] + s_hit * q[:, 1]
            z = origin[2] + s_hit * q[:, 2]
        candidates = np.flatnonzero((s_hit > 0) & (y * y + z * z < (radius + 0.051) ** 2))
        rays = unit_rays(p_L[candidates]) @ H.R
        with np.errstate(divide="ignore", invalid="ignore"):
            s_hit = -origin[0] / rays[:, 0]
        hit = origin + s_hit[:, None] * rays
        out: NDArray[np.intp] = candidates[
            (s_hit > 0) & (np.hypot(hit[:, 1], hit[:, 2]) < radius + 0.05)]
        return out

    return positions(block, scan.p_L.shape[0])


@dataclass(frozen=True)
class _Returns:
    """The returns :func:`model_labels` chooses from, with what does not depend on the
    estimate: computed once for every round of a fit."""

    p_L: FloatArray
    """(N, 3) returns in L (as measured)"""
    cos: FloatArray
    """(N,) cosine of each return's platter angle"""
    sin: FloatArray
    """(N,) sine of each return's platter angle"""
    rho: FloatArray
    """(N,) ranges (m, as measured)"""
    rays: FloatArray
    """(N, 3) unit rays in L"""
    key: FloatArray
    """(N,) a fixed random number per return: a round keeps, of the returns it labels, those
    of the smallest keys (:func:`_kept`)"""

    @classmethod
    def of(cls, scan: SpinScan, idx: NDArray[np.intp]) -> _Returns:
        """The returns ``idx`` of ``scan``."""
        p_L, phi = scan.p_L[idx], scan.phi[idx]
        rho = np.linalg.norm(p_L, axis=1)
        rays = p_L / np.maximum(rho, 1e-12)[:, None]  # unit_rays, from the ranges known
        return cls(p_L, np.cos(phi), np.sin(phi), rho, rays, fixed_keys(idx.shape[0]))

    def every(self, k: int) -> _Returns:
        """Every ``k``-th of these returns (views, no copy)."""
        return _Returns(self.p_L[::k], self.cos[::k], self.sin[::k], self.rho[::k],
                        self.rays[::k], self.key[::k])


def fixed_keys(n: int) -> FloatArray:
    """(n,) the fixed random key of each of n returns (:func:`_kept`)."""
    return np.asarray(np.random.default_rng(0).random(n), dtype=np.float64)


def _kept(idx: NDArray[np.intp], key: FloatArray, most: int) -> NDArray[np.intp]:
    """``idx`` (increasing positions), or the ``most`` of them whose ``key`` is smallest, in
    increasing order: a subset that two rounds labelling nearly the same returns nearly share.
    A subset drawn afresh from each round's returns would differ wholly whenever one return
    did, and the fit's estimate with it (by up to 0.7σ in ty from one round to the next, on
    a cube scan of the realistic station)."""
    if idx.size <= most:
        return idx
    out: NDArray[np.intp] = np.sort(idx[np.argpartition(key[idx], most)[:most]])
    return out


def model_labels(
    returns: _Returns, v: FloatArray, pose: FloatArray, edge: float, platter_radius: float,
    noise: float, *, most: tuple[int, int] = (FIT_POINTS, PLATTER_POINTS),
) -> tuple[_Faces, FloatArray]:
    """The returns of the cube's faces and of the platter top, chosen by casting each return's
    ray against the model (an upright cube of ``edge`` at ``pose`` = centre y, z and yaw in D,
    on the platter top x_D = 0, under the estimate ``v``): a face's returns are those whose ray
    enters the cube through that face at least :data:`MARGIN` from its edges; the platter's,
    those whose ray meets the platter inside its rim, the cube missed by :data:`MARGIN`. Of
    them, those whose range is within max(6σ, 5 mm) of the model's (a window symmetric about
    the model: mixed pixels and strays out, no selection on the noise). Returns the faces and
    the platter's returns (as measured, in L): at most ``most`` of each, fixed random subsets
    (:data:`FIT_POINTS`, :data:`PLATTER_POINTS`)."""
    window = max(6.0 * noise if math.isfinite(noise) else 0.0, 0.005)
    cast = _Cast(returns, v, pose, edge, platter_radius, window)
    n = returns.p_L.shape[0]
    label, on_face, on_plate, close, heights = stacked(by_blocks(cast, n))
    if np.count_nonzero(on_plate & close) < MIN_PLATTER and heights.size:
        # the estimate's level is off by more than the window allows: centre the window on
        # where the platter's returns read (:meth:`_Cast.platter`)
        level = float(np.median(heights))
        close = np.concatenate(by_blocks(lambda rows: cast.close_to(rows, level), n))
    most_faces, most_platter = most
    faces_idx = _kept(np.flatnonzero(on_face), returns.key, most_faces)
    plate_idx = _kept(np.flatnonzero(on_plate & close), returns.key, most_platter)
    found = [f for f in range(1, 6) if np.count_nonzero(label[faces_idx] == f) >= 30]
    if len(found) < MIN_FACES or plate_idx.size < MIN_PLATTER:
        raise FineTuningError(
            f"the known-size cube fit with the range model needs {MIN_FACES} faces of the cube "
            f"with 30 returns and the platter around it: found {len(found)} faces and "
            f"{plate_idx.size} returns of the platter"
        )
    lab = label[faces_idx]
    cy, cz, yaw = (float(a) for a in pose[:3])
    # the labels of :func:`_label`: 1 the top, 2/3 the −u/+u sides, 4/5 the −w/+w sides
    faces = _Faces(
        p_L=returns.p_L[faces_idx], cos=returns.cos[faces_idx], sin=returns.sin[faces_idx],
        rays=returns.rays[faces_idx], side=lab >= 2, across_u=lab < 4,
        sign=np.where(lab % 2 == 1, 1.0, -1.0), pose=np.array([cy, cz, yaw, edge]),
        noise=noise, faces=len(found),
    )
    platter: FloatArray = returns.p_L[plate_idx]
    return faces, platter


class _Cast:
    """:func:`model_labels`'s casting of the returns' rays against the model, a block of
    returns at a time (:func:`calstation.engine.blocks.by_blocks`)."""

    def __init__(self, returns: _Returns, v: FloatArray, pose: FloatArray, edge: float,
                 platter_radius: float, window: float) -> None:
        self.returns, self.edge, self.radius, self.window = returns, edge, platter_radius, window
        self.H = Extrinsics.from_vector(v[: len(PARAMETER_NAMES)])
        self.model = RangeModel.from_vector(v)
        self.centre = (float(pose[0]), float(pose[1]))
        self.yaw = float(pose[2])

    def rays(self, rows: slice) -> tuple[FloatArray, FloatArray]:
        """The lidar's position and the unit rays of the returns ``rows``, in D."""
        r, H = self.returns, self.H
        cos, sin = r.cos[rows], r.sin[rows]
        o = _spun(np.broadcast_to(-(H.t @ H.R), (cos.shape[0], 3)), cos, sin)
        return o, _turned(r.rays[rows], H, cos, sin)

    def __call__(self, rows: slice) -> tuple[NDArray[np.int64], NDArray[np.bool_],
                                             NDArray[np.bool_], NDArray[np.bool_], FloatArray]:
        """Of the returns ``rows``: the face each ray enters (:func:`_box_entry`'s label),
        which are a face's returns within the window, which meet the platter, which of them
        read within the window of its top, and the heights of those that may be the
        platter's (:meth:`platter`)."""
        o, d = self.rays(rows)
        cy, cz = self.centre
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        # the cube's frame: x up, u = (cos yaw, sin yaw) and w = (−sin yaw, cos yaw) across
        ol = np.column_stack([o[:, 0], c * (o[:, 1] - cy) + s * (o[:, 2] - cz),
                              -s * (o[:, 1] - cy) + c * (o[:, 2] - cz)])
        dl = np.column_stack([d[:, 0], c * d[:, 1] + s * d[:, 2], -s * d[:, 1] + c * d[:, 2]])
        label, cube_range, shadow = _cube_entries(ol, dl, self.edge)
        measured = self.model.ranges(self.returns.rho[rows])
        on_face = (label > 0) & (np.abs(measured - cube_range) <= self.window)
        return (label, on_face, *self.platter(o, d, measured, shadow))

    def platter(
        self, o: FloatArray, d: FloatArray, measured: FloatArray, shadow: FloatArray,
    ) -> tuple[NDArray[np.bool_], NDArray[np.bool_], FloatArray]:
        """The returns whose ray (from ``o`` along unit ``d``, in D) meets the platter top
        inside its rim, the cube's shadow missed; which of them read within the window of the
        top; and the heights above the top of those within :data:`LEVEL_SEARCH` of it.

        The top is the plane x_D = 0 of the estimate; when fewer than :data:`MIN_PLATTER` of
        its returns read within the window there, the estimate's level is off by more than the
        window allows (at 30° of pitch the rays meet the platter at grazing angles, and 2 mm of
        level is 5 mm of range): the window is then centred on where the platter's returns
        read, the median of those heights (:meth:`close_to`), and the fit brings the estimate
        there. The median is of every such return, so the window is still symmetric about a
        model and chooses none by its noise."""
        with np.errstate(divide="ignore", invalid="ignore"):
            plate_range = -o[:, 0] / d[:, 0]
            at = o + plate_range[:, None] * d
        on_plate = ~np.isfinite(shadow) & (plate_range > 0) & (
            np.hypot(at[:, 1], at[:, 2]) <= self.radius - MARGIN)
        close = np.abs(measured - plate_range) <= self.window
        height = o[:, 0] + measured * d[:, 0]  # each return's height above the estimate's top
        return on_plate, close, height[on_plate & (np.abs(height) <= LEVEL_SEARCH)]

    def close_to(self, rows: slice, level: float) -> NDArray[np.bool_]:
        """Which of the returns ``rows`` read within the window of the platter top at
        ``level`` (m above the estimate's)."""
        o, d = self.rays(rows)
        measured = self.model.ranges(self.returns.rho[rows])
        with np.errstate(divide="ignore", invalid="ignore"):
            shifted = (level - o[:, 0]) / d[:, 0]
        out: NDArray[np.bool_] = np.abs(measured - shifted) <= self.window
        return out


MIN_PLATTER = 200
"""Platter returns the known-size fit with a range model needs around the cube."""

LEVEL_SEARCH = 0.03
"""How far (m) from the estimate's platter top the platter's returns are looked for when too
few read within the window there: a start's level is within millimetres (the box cost's, or
the spin target's), the floor and the background far below."""


def _cube_entries(
    origin: FloatArray, direction: FloatArray, edge: float,
) -> tuple[NDArray[np.int64], FloatArray, FloatArray]:
    """:func:`_box_entry` of the rays (in the cube's frame) into the cube of ``edge`` with
    :data:`MARGIN` from its faces' edges (the face, the range), and the range into its shadow,
    the cube grown by :data:`MARGIN` (inf when missed). Only the rays that can meet the shadow
    are cast (:func:`_may_meet`, a fifth of those near the platter, tested in single
    precision: a tenth of a micrometre against its millimetre to spare); the rest miss both."""
    cast = _may_meet(origin.astype(np.float32), direction.astype(np.float32), edge)
    label = np.zeros(origin.shape[0], dtype=np.int64)
    cube_range = np.full(origin.shape[0], np.inf)
    shadow = np.full(origin.shape[0], np.inf)
    o, d = origin[cast], direction[cast]
    label[cast], cube_range[cast] = _box_entry(o, d, edge, MARGIN)
    shadow[cast] = _box_entry(o, d, edge + 2 * MARGIN, 0.0, floor=-MARGIN)[1]
    return label, cube_range, shadow


def _may_meet(
    origin: NDArray[np.floating], direction: NDArray[np.floating], edge: float
) -> NDArray[np.intp]:
    """Positions of the rays (in the cube's frame) that may meet the cube of ``edge`` grown by
    :data:`MARGIN` (``_box_entry(…, edge + 2·MARGIN, 0, floor=−MARGIN)``): the part of each ray
    ahead of its origin within the box's heights passes within the circle round its footprint
    (1 mm to spare). Level rays are all kept."""
    low, high = -MARGIN, edge + 2 * MARGIN
    radius = math.sqrt(2.0) * (0.5 * edge + MARGIN) + 0.001
    up = direction[:, 0]
    level = np.abs(up) < 1e-9
    with np.errstate(divide="ignore", invalid="ignore"):  # a level ray's heights: ±inf
        t_low = (low - origin[:, 0]) / up
        t_high = (high - origin[:, 0]) / up
        first = np.maximum(np.minimum(t_low, t_high), 0.0)
        last = np.maximum(t_low, t_high)
        # the segment's ends across the axis, and its point nearest the footprint's centre
        a = origin[:, 1:] + first[:, None] * direction[:, 1:]
        b = origin[:, 1:] + last[:, None] * direction[:, 1:]
        ab = b - a
        along = np.clip(-np.einsum("ij,ij->i", a, ab)
                        / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-30), 0.0, 1.0)
        nearest = a + along[:, None] * ab
        near = (first <= last) & (np.einsum("ij,ij->i", nearest, nearest) < radius**2)
    out: NDArray[np.intp] = np.flatnonzero(level | near)
    return out


def _box_entry(
    origin: FloatArray, direction: FloatArray, edge: float, margin: float, floor: float = 0.0,
) -> tuple[NDArray[np.int64], FloatArray]:
    """Where rays (origin, direction (N, 3) in the cube's frame: x up, then across) enter the
    box x ∈ [floor, edge], u, w ∈ [−edge/2, edge/2]: (N,) the face (1 the top, 2/3 −u/+u,
    4/5 −w/+w; 0 when missed, through the bottom, or within ``margin`` of the face's edges)
    and (N,) the range to it (inf when missed)."""
    lo = np.array([floor, -0.5 * edge, -0.5 * edge])
    hi = np.array([edge, 0.5 * edge, 0.5 * edge])
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - origin) / direction
        t2 = (hi - origin) / direction
    near = np.nan_to_num(np.minimum(t1, t2), nan=-np.inf)
    far = np.nan_to_num(np.maximum(t1, t2), nan=np.inf)
    enter, leave = near.max(axis=1), far.min(axis=1)
    axis = near.argmax(axis=1)
    rows = np.arange(origin.shape[0])
    hit = (enter <= leave) & (enter > 0)
    point = origin + enter[:, None] * direction
    # entering through the face at the upper end of an axis means moving down along it
    upper = direction[rows, axis] < 0
    label = np.where(axis == 0, np.where(upper, 1, 0), 2 * axis + upper).astype(np.int64)
    inside = np.ones(origin.shape[0], dtype=bool)
    for k in range(3):
        inside &= (axis == k) | ((point[:, k] >= lo[k] + margin) & (point[:, k] <= hi[k] - margin))
    label = np.where(hit & inside, label, 0)
    return label, np.where(hit, enter, np.inf)
