"""The paper's shape cost on the QA cube's spin scan (paper §III-B-1): the cube's returns
reconstructed in frame D under a candidate H, segmented, cleaned and boxed, as least-squares
residuals (:class:`ShapeCost`), and the returns it is evaluated on (:func:`near_cube`,
:func:`subsample`). The shape strategy (:mod:`calstation.engine.shape`) minimises it."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from calstation.engine.frames import Extrinsics, FloatArray
from calstation.engine.geometry import (
    largest_cluster,
    minimal_obb,
    radius_outlier_mask,
    segment_above_platter,
    signed_face_distances,
    upright_box,
)
from calstation.engine.settings import CubeGeometry, ShapeSettings


class ShapeCost:
    """The paper's cost on a fixed subset of cube-scan returns, as least-squares residuals.

    Residuals: ``d_k/√N`` for the N segmented, cleaned points (0 for the others, so the vector
    keeps its length) followed by ``s_i − s``; their sum of squares is ``C1 + C2``.
    """

    def __init__(
        self,
        p_L: FloatArray,
        phi: FloatArray,
        cube: CubeGeometry,
        settings: ShapeSettings,
        *,
        platter_radius: float,
        density_scale: float,
        box: str = "upright",
    ) -> None:
        self.p_L, self.phi = p_L, phi
        self._cos, self._sin = np.cos(phi), np.sin(phi)
        self.edge = cube.edge
        self.settings = settings
        self.platter_radius = platter_radius
        self.outlier_radius = settings.outlier_radius * density_scale
        self._radius_from_data = False
        self.box = box
        self.evaluations = 0
        self.frozen: NDArray[np.bool_] | None = None
        self._frozen_idx: NDArray[np.intp] | None = None
        self.last_edge_errors = np.zeros(3)

    def freeze(self, H: Extrinsics | None) -> None:
        """Hold the cube's point set fixed at its segmentation under H (None: re-segment at
        every evaluation, as the paper does). A fixed set keeps the residuals continuous."""
        self.frozen = None if H is None else self.cloud(H)[1]
        self._frozen_idx = None if self.frozen is None else np.flatnonzero(self.frozen)

    def to_dynamic(self, H: Extrinsics, idx: NDArray[np.intp] | None = None) -> FloatArray:
        """The returns (all, or those at ``idx``) in D under H: :func:`lidar_to_dynamic` with
        the platter angles' cosines and sines computed once."""
        p, c, s = (self.p_L, self._cos, self._sin) if idx is None else (
            self.p_L[idx], self._cos[idx], self._sin[idx])
        p_P = (p - H.t) @ H.R
        y = c * p_P[:, 1] + s * p_P[:, 2]
        z = -s * p_P[:, 1] + c * p_P[:, 2]
        return np.column_stack([p_P[:, 0], y, z])

    def cloud(self, H: Extrinsics) -> tuple[FloatArray, NDArray[np.bool_]]:
        """(N, 3) all returns in D and the mask of the segmented, cleaned cube points."""
        p_D = self.to_dynamic(H)
        seg = segment_above_platter(
            p_D,
            margin=self.settings.segment_margin,
            radius=self.platter_radius,
            height=3.0 * self.edge,
        )
        idx = np.flatnonzero(seg)
        if not self._radius_from_data:
            self._scale_radius_to_density(p_D[idx])
        keep = radius_outlier_mask(p_D[idx], self.outlier_radius, self.settings.outlier_neighbours)
        if self.box == "upright":
            keep[keep] = largest_cluster(p_D[idx[keep]])
        mask = np.zeros(p_D.shape[0], dtype=bool)
        mask[idx[keep]] = True
        return p_D, mask

    def _scale_radius_to_density(self, points: FloatArray) -> None:
        """Widen the outlier radius to the scan's real density, once (the first segmentation).

        The paper's 1 mm for 8 neighbours assumes its sensor's density; at a lower line rate the
        cube's own returns are farther apart than that and the filter removed the cube (180
        lines/s: too few returns left). When the configured radius would drop most returns, it
        becomes 2.5× the median distance to the ``outlier_neighbours``-th neighbour, so isolated
        returns still go.
        """
        k = self.settings.outlier_neighbours
        self._radius_from_data = True
        if k <= 0 or points.shape[0] <= k + 1:
            return
        dist, _ = cKDTree(points).query(points, k=k + 1, workers=-1)
        if np.mean(dist[:, -1] <= self.outlier_radius) >= 0.5:
            return  # the configured radius keeps most returns: the scan is dense enough
        self.outlier_radius = max(self.outlier_radius, 2.5 * float(np.median(dist[:, -1])))

    def residuals_of(self, H: Extrinsics) -> FloatArray:
        """C1 and C2 terms as a fixed-length residual vector."""
        self.evaluations += 1
        if self.frozen is not None:
            mask = self.frozen
            pts = self.to_dynamic(H, self._frozen_idx)
        else:
            p_D, mask = self.cloud(H)
            pts = p_D[mask]
        out = np.zeros(self.p_L.shape[0] + 3)
        n = pts.shape[0]
        if n < 50:
            out[-3:] = self.edge  # no cube: as bad as a missing cube
            return out
        fit = upright_box if self.box == "upright" else minimal_obb
        centre, axes, extents = fit(pts)
        d = signed_face_distances(pts, centre, axes, extents)
        out[: self.p_L.shape[0]][mask] = d / math.sqrt(n)
        self.last_edge_errors = extents - self.expected_extents(axes)
        if self.box == "minimal":
            out[-3:] = self.last_edge_errors
        # upright: C1 only. Its faces are medians, and while the two half-turns disagree each
        # face is doubled; the median then sits between the copies and the edge lengths no
        # longer grow with the calibration error (C2 pulled the optimiser the wrong way).
        return out

    def expected_extents(self, axes: FloatArray) -> FloatArray:
        """(3,) true extents along the box axes: the segmentation cuts ``segment_margin`` off
        the bottom, so the axis closest to X_D expects ``s − margin``."""
        out = np.full(3, self.edge)
        vertical = int(np.argmax(np.abs(axes[0, :])))
        out[vertical] = self.edge - self.settings.segment_margin
        return out


def near_cube(
    p_L: FloatArray, phi: FloatArray, H: Extrinsics, cube: CubeGeometry, platter_radius: float
) -> tuple[FloatArray, FloatArray]:
    """The returns ((N, 3) in L, (N,) φ) in a generous region above the platter under H (the
    start may be a few cm off). Height along the axis and distance from it do not depend on
    the platter angle: the test needs no turn into D."""
    q = p_L @ H.R
    q -= H.t @ H.R
    r2 = np.einsum("ij,ij->i", q[:, 1:], q[:, 1:])
    height = 3.0 * cube.edge + 0.05
    near = (q[:, 0] > 0.0) & (q[:, 0] < height) & (r2 < (platter_radius + 0.05) ** 2)
    return p_L[near], phi[near]


def subsample(
    p_L: FloatArray, phi: FloatArray, max_points: int
) -> tuple[FloatArray, FloatArray, float]:
    """A fixed random subset of at most ``max_points`` returns, and the density scale
    √(all / subset) for the outlier radius."""
    n_all = p_L.shape[0]
    if n_all > max_points:
        pick = np.sort(np.random.default_rng(0).choice(n_all, max_points, replace=False))
        p_L, phi = p_L[pick], phi[pick]
    return p_L, phi, math.sqrt(n_all / p_L.shape[0])
