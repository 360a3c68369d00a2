"""The QA cube's returns in a spin scan under one H: the platter's level, the ring of platter
around the cube and the cube's cleaned returns (density outlier removal, largest cluster), found
once and kept with the scan's returns, so that the checks and fits that follow under the same H
(or one within a millimetre of it) take them instead of segmenting again (DESIGN §5, §8)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from calstation.engine.blocks import by_blocks, stacked
from calstation.engine.frames import Extrinsics, FloatArray, lidar_to_dynamic
from calstation.engine.geometry import (
    density_outlier_mask,
    largest_cluster,
    level_of_heights,
    veil_mask,
    whole_lines,
)

SEGMENT_MARGIN = 0.005
"""Cube points are those more than 5 mm above the platter top (the OBB height adds it back)."""

PLATTER_WINDOW = 0.02
"""The platter top is looked for within this distance of x_D = 0 (m)."""
RING_BAND = 0.004
"""The platter plane beside the cube is fitted to the returns within this distance of its
level (m)."""
RING_POINTS = 150_000
"""At most this many of those, a regular subset (the platter gives ~0.75 M in a 3 M scan)."""
CUBE_RETURNS = 400_000
"""Returns above the platter the segmentation (density outlier removal, largest cluster) and
everything after it in the check (the paper's box, the faces, the twist) use at most: beyond,
every k-th scan line of them. The check's cost is then bounded whatever the cube's size or the
scan's turns: a 0.1 m cube gives ~110 000 a turn at 1000 lines/s (3.5 turns are used whole;
the twist's own cap, :data:`calstation.engine.twist.TWIST_POINTS`, was reached at ~5), a
0.4 m cube centred on the platter ~1.3 M, whose check took a minute. The known-size cube fit
labels all of them (:attr:`CubeCloud.p_L`)."""


@dataclass(frozen=True)
class CubeCloud:
    """The cube's returns under one H, found from a spin scan's returns."""

    level: float
    """the platter top's height along X_D"""
    p_ring: FloatArray
    """(M, 3) a regular subset of the platter ring's returns in D, heights from ``level``"""
    p_L: FloatArray
    """(K, 3) the returns above the platter near the axis, in L"""
    phi: FloatArray
    """(K,) their platter angles"""
    idx: NDArray[np.intp]
    """positions in ``p_L`` of the cube's cleaned returns"""
    pts: FloatArray
    """(n, 3) the cube's cleaned returns in D, heights from ``level``"""
    window: NDArray[np.intp] = field(default_factory=lambda: np.zeros(0, dtype=np.intp))
    """positions in the scan's returns of those the platter's level was found from"""
    ring: NDArray[np.intp] = field(default_factory=lambda: np.zeros(0, dtype=np.intp))
    """positions in the scan's returns of ``p_ring``"""
    veil: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, dtype=bool))
    """(n,) True for those of ``pts`` on a veil (:func:`calstation.engine.geometry.veil_mask`)"""
    above: NDArray[np.intp] = field(default_factory=lambda: np.zeros(0, dtype=np.intp))
    """(K,) positions in the scan's returns of ``p_L``"""


def segment_cube(
    p_L: FloatArray, phi: FloatArray, H: Extrinsics, s: float, platter_radius: float,
    most: int | None = None,
) -> CubeCloud:
    """Find the platter and the cube's returns under H (the cube check's segmentation), the
    cube's cleaned returns among at most about ``most`` of those above the platter (whole
    scan lines; :data:`CUBE_RETURNS` unless given)."""
    # height along the axis and distance from it do not depend on the platter angle: find the
    # platter and the returns the steps below can use before turning any by its angle; the
    # distance from the axis once, of every return the three tests below may take (the
    # platter's level lies within PLATTER_WINDOW of x_P = 0)
    near, x_near, r2 = along_axis(p_L, H, -PLATTER_WINDOW - RING_BAND, 3 * s + PLATTER_WINDOW)
    inside = r2 < (platter_radius - 0.005) ** 2
    # measure from the platter as seen, not from x_D = 0: a calibration's origin along the axis
    # is a gauge (the shape strategy holds ty), and a few millimetres there would otherwise
    # lift the platter itself above the segmentation cut
    in_window = (np.abs(x_near) < PLATTER_WINDOW) & inside
    window = near[in_window]
    level = level_of_heights(x_near[in_window])
    x_near -= level
    above = near[(x_near > SEGMENT_MARGIN) & (x_near < 3 * s) & (r2 < platter_radius**2)]
    ring = near[(np.abs(x_near) < RING_BAND) & inside]
    ring = ring[:: max(1, -(-ring.size // RING_POINTS))]
    p_ring = lidar_to_dynamic(p_L[ring], phi[ring], H)
    p_ring[:, 0] -= level
    p_above, phi_above = p_L[above], phi[above]
    used = whole_lines(p_above, CUBE_RETURNS if most is None else most)
    p_D = lidar_to_dynamic(p_above[used], phi_above[used], H)
    p_D[:, 0] -= level
    keep = np.flatnonzero(density_outlier_mask(p_D))
    keep = keep[largest_cluster(p_D[keep])]
    return CubeCloud(level, p_ring, p_above, phi_above, used[keep], p_D[keep], window, ring,
                     veil_mask(p_L, above[used[keep]]), above)


def along_axis(
    p_L: FloatArray, H: Extrinsics, low: float, high: float
) -> tuple[NDArray[np.intp], FloatArray, FloatArray]:
    """The returns ((N, 3) in L) whose height along the axis under H lies between ``low`` and
    ``high`` (m, from x_P = 0): their positions, their heights and their squared distances from
    the axis. Neither depends on the platter angle, so no return is turned by it. A block of
    returns at a time (:mod:`calstation.engine.blocks`)."""
    t_P = H.t @ H.R

    def block(rows: slice) -> tuple[NDArray[np.intp], FloatArray, FloatArray]:
        x = p_L[rows] @ H.R[:, 0]
        x -= t_P[0]
        idx = np.flatnonzero((x > low) & (x < high))
        yz = p_L[rows][idx] @ H.R[:, 1:]
        yz -= t_P[1:]
        return idx + rows.start, x[idx], np.einsum("ij,ij->i", yz, yz)

    idx, x, r2 = stacked(by_blocks(block, p_L.shape[0]))
    return idx.astype(np.intp, copy=False), x, r2


def moved_cloud(
    cloud: CubeCloud, p_L: FloatArray, phi: FloatArray, H: Extrinsics, *, corrected: bool = False
) -> CubeCloud:
    """``cloud``'s returns, found under another H within a millimetre of this one, under H:
    the platter's level from the same returns and the cube's cleaned returns and the ring
    turned into D by H, without segmenting again (``p_L``, ``phi``: the scan's returns
    ``cloud`` was found in). The level, a median refined to the returns within 3 mm of it,
    does not depend on the window's edges. With ``corrected``, ``p_L`` holds the same returns
    moved along their rays by a range correction of a few millimetres at most (the incidence
    bias's): the cloud's returns and its veil are taken from them."""
    t_P = H.t @ H.R
    level = level_of_heights(p_L[cloud.window] @ H.R[:, 0] - t_P[0])
    p_ring = lidar_to_dynamic(p_L[cloud.ring], phi[cloud.ring], H)
    p_ring[:, 0] -= level
    if corrected:
        cloud = replace(cloud, p_L=p_L[cloud.above],
                        veil=veil_mask(p_L, cloud.above[cloud.idx]))
    pts = lidar_to_dynamic(cloud.p_L[cloud.idx], cloud.phi[cloud.idx], H)
    pts[:, 0] -= level
    return replace(cloud, level=level, p_ring=p_ring, pts=pts)


MEMO_KEY = "cube_cloud"
"""The key of a scan's memo under which :func:`cube_cloud` keeps its last segmentation."""


def _cloud_key(H: Extrinsics, s: float, platter_radius: float) -> tuple[bytes, float, float]:
    return H.as_vector().tobytes(), s, platter_radius


def keep_cloud(
    memo: dict[str, object], cloud: CubeCloud, H: Extrinsics, s: float, platter_radius: float
) -> None:
    """Keep ``cloud``, the cube's returns under H (cube edge ``s``), in ``memo`` as
    :func:`cube_cloud` keeps the one it finds."""
    memo[MEMO_KEY] = (_cloud_key(H, s, platter_radius), cloud)


def cube_cloud(
    p_L: FloatArray,
    phi: FloatArray,
    H: Extrinsics,
    s: float,
    platter_radius: float,
    memo: dict[str, object] | None,
    *,
    nearby: bool = False,
) -> CubeCloud:
    """:func:`segment_cube`, taken from ``memo`` when it holds the one under the same H, cube
    and platter (with ``nearby``, under any H: :func:`moved_cloud` turns it to this one), and
    kept there."""
    key = _cloud_key(H, s, platter_radius)
    found = memo.get(MEMO_KEY) if memo is not None else None
    kept_key, kept = found if isinstance(found, tuple) else (None, None)
    if isinstance(kept, CubeCloud) and kept_key == key:
        return kept
    if isinstance(kept, CubeCloud) and nearby and isinstance(kept_key, tuple) \
            and kept_key[1:] == key[1:]:
        cloud = moved_cloud(kept, p_L, phi, H)
    else:
        cloud = segment_cube(p_L, phi, H, s, platter_radius)
    if memo is not None:
        keep_cloud(memo, cloud, H, s, platter_radius)
    return cloud

