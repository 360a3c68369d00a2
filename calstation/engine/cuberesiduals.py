"""The known-size cube fit's residuals (:mod:`calstation.engine.cubefit`): each labelled
return's range error against an upright cube of the recipe's edge on the platter, with and
without the lidar's range model, and the platter's returns against its top; the latter's
Jacobian in closed form."""

from __future__ import annotations

import math

import numpy as np

from calstation.engine.blocks import pool
from calstation.engine.cubecast import _Faces, _turned
from calstation.engine.frames import (
    PARAMETER_NAMES,
    Extrinsics,
    FloatArray,
    rotation_derivative,
    rowdot,
)
from calstation.engine.kept import Kept
from calstation.engine.rangemodel import (
    INCIDENCE,
    LEAST_COSINE_KNOWN,
    OFFSET,
    SCALE,
    correct_vector,
    incidence_shape,
    incidence_shape_slope,
    unit_rays,
)
from calstation.engine.twist import GRAZING_FACE, away_from_grazing


class RangeErrors:
    """Range errors of the labelled returns against an upright cube of edge ``edge``, as a
    function of x = (H's free parameters, centre y, centre z, yaw, top height)."""

    def __init__(self, faces: _Faces, base: FloatArray, free: list[int], edge: float) -> None:
        self.f, self.base, self.free, self.edge = faces, base, free, edge

    def H(self, x: FloatArray) -> Extrinsics:
        v = self.base.copy()
        v[self.free] = x[: len(self.free)]
        return Extrinsics.from_vector(v)

    def __call__(self, x: FloatArray, edge: float | None = None) -> FloatArray:
        f = self.f
        H = self.H(x)
        q = _turned(f.p_L - H.t, H, f.cos, f.sin)
        r = _turned(f.rays, H, f.cos, f.sin)
        cy, cz, yaw, top = x[len(self.free):]
        c, s = math.cos(yaw), math.sin(yaw)
        ny, nz = side_normals(f, c, s)
        half = 0.5 * (self.edge if edge is None else edge)
        dist = np.where(f.side, ny * (q[:, 1] - cy) + nz * (q[:, 2] - cz) - half, q[:, 0] - top)
        cosine = np.where(f.side, ny * r[:, 1] + nz * r[:, 2], r[:, 0])
        out: FloatArray = dist / away_from_grazing(cosine)
        return out


class RangeSizeErrors:
    """The range errors of the known-size fit when the lidar's range model is estimated too:
    the labelled returns against an upright cube of edge ``edge`` standing on the platter (its
    top at ``edge`` above the origin), and the platter's returns against a plane perpendicular
    to the axis — at a level of their own, or with the scale error at the origin (the cube's
    height, a known length, is what sets the scale) — every return first corrected along its
    ray by the range terms. x = (the free parameters of the estimated vector, indices ``free``
    of :data:`~calstation.engine.rangemodel.ESTIMATED_NAMES`; centre y, centre z, yaw; with
    ``dish``, the platter's dish c, and with its level free, the platter's height at the cube:
    :attr:`shape`)."""

    def __init__(self, faces: _Faces, platter: FloatArray, base: FloatArray, free: list[int],
                 edge: float, dish: bool = False) -> None:
        self.f, self.base, self.free, self.edge = faces, base, free, edge
        self.platter = platter
        self.platter_rays = unit_rays(platter)
        # the ranges, corrected at every evaluation, are measured once
        self.rho = np.linalg.norm(faces.p_L, axis=-1)
        self.platter_rho = np.linalg.norm(platter, axis=-1)
        self.level_free = SCALE not in free
        """the platter's level free, unless the scale error is fitted: then the cube's height
        above the platter is the known length that sets it (the platter and the cube must read
        alike: one finish)"""
        self.dish = dish
        """the platter's shape fitted, last in x (else flat; see :func:`range_size_fit`): its
        top at c·(r² − r_c²) along the axis (r a return's distance from the axis, r_c the cube's
        centre's) and, with its level free, at a height of its own by the cube. A cube on a
        dish stands where the dish is under its footprint, which is not where the platter's
        mean plane is, nor where the dish is under the cube's centre: a level in range units
        alone (the platter's finish) left a height there read through the rays' angles with
        the platter, as a tilt (rz 63 µrad off at 0.4 mm of dish on a simulated platter whose
        cube stands at the dish's mean plane)"""
        self.shape = (2 if self.level_free else 1) if dish else 0
        """how many of x's last parameters are the platter's shape"""
        self._kept = Kept()
        """the last evaluation's turned rays (by H), faces (by the estimated vector and the
        yaw) and platter (by the estimated vector): a finite-difference step in the cube's
        centre, its yaw or a range term leaves some of them as they were"""

    def vector(self, x: FloatArray) -> FloatArray:
        v = self.base.copy()
        v[self.free] = x[: len(self.free)]
        return v

    def H(self, x: FloatArray) -> Extrinsics:
        return Extrinsics.from_vector(self.vector(x)[: len(PARAMETER_NAMES)])

    def _normals(self, x: FloatArray, H: Extrinsics) -> tuple[FloatArray, FloatArray, FloatArray]:
        """The side faces' normals (y, z in D) under the pose of ``x``, and each face return's
        cosine with its surface's normal."""
        f = self.f
        r = self._kept.get("rays", H.as_vector().tobytes(),
                       lambda: (_turned(f.rays, H, f.cos, f.sin),))[0]
        yaw = float(x[len(self.free) + 2])
        c, s = math.cos(yaw), math.sin(yaw)
        ny, nz = side_normals(f, c, s)
        return ny, nz, np.where(f.side, ny * r[:, 1] + nz * r[:, 2], r[:, 0])

    def _platter_shape(self, x: FloatArray) -> tuple[float, float]:
        """The platter's dish c and its height at the cube in ``x`` (0 where not fitted)."""
        shape = [float(v) for v in x[len(self.free) + 3:]] + [0.0, 0.0]
        return shape[0], shape[1]

    def cosines(self, x: FloatArray) -> FloatArray:
        """(N,) each return's cosine with its surface's normal: the faces', then the
        platter's."""
        H = self.H(x)
        return np.concatenate([self._normals(x, H)[2], self.platter_rays @ H.R[:, 0]])

    def __call__(self, x: FloatArray, edge: float | None = None) -> FloatArray:
        f = self.f
        v = self.vector(x)
        H = Extrinsics.from_vector(v[: len(PARAMETER_NAMES)])
        size = self.edge if edge is None else edge
        cy, cz = x[len(self.free):len(self.free) + 2]

        def faces() -> tuple[FloatArray, ...]:
            ny, nz, cosine = self._normals(x, H)
            shape = incidence_shape(cosine, LEAST_COSINE_KNOWN)
            q = _turned(correct_vector(f.p_L, v, shape, self.rho) - H.t, H, f.cos, f.sin)
            return ny, nz, cosine, q

        def on_platter() -> tuple[FloatArray, ...]:
            down = self.platter_rays @ H.R[:, 0]
            q = (correct_vector(self.platter, v, incidence_shape(down, LEAST_COSINE_KNOWN),
                                self.platter_rho) - H.t) @ H.R
            a = away_from_grazing(down)
            return q[:, 0] / a, (q[:, 1] ** 2 + q[:, 2] ** 2) / a, 1.0 / a

        ny, nz, cosine, q = self._kept.get("faces", v.tobytes() + x[len(self.free) + 2].tobytes(),
                                       faces)
        dist = np.where(f.side, ny * (q[:, 1] - cy) + nz * (q[:, 2] - cz) - 0.5 * size,
                        q[:, 0] - size)
        height, across, inverse = self._kept.get("platter", v.tobytes(), on_platter)
        # the platter's shape (:attr:`dish`), heights turned into ranges along the rays
        dish, level = self._platter_shape(x)
        platter = height - dish * (across - (cy * cy + cz * cz) * inverse) - level * inverse
        if self.level_free:
            # about their mean: the platter gives the axis's direction; its level is free, as
            # a platter of another finish reads at another range than the cube (the cube's
            # top, at its edge above the origin, gives the origin)
            platter = platter - platter.mean()
        out: FloatArray = np.concatenate([dist / away_from_grazing(cosine), platter])
        if not self.level_free:
            # in the lidar's own units: a corrected return is its measured range over 1 + k,
            # so residuals of corrected returns would shrink the range noise as k grows, and
            # least squares would lean k up by about (noise / the fixtures' depth)² — 400 ppm
            # at 1 mm of noise; times 1 + k, the noise's share no longer depends on k
            out *= 1.0 + float(v[SCALE])
        return out

    def jac(self, x: FloatArray) -> FloatArray:
        """(m, n) the derivatives of the residuals of :meth:`__call__` by ``x``, in closed
        form: a finite difference cost an evaluation of every residual per parameter."""
        v = self.vector(x)
        H = Extrinsics.from_vector(v[: len(PARAMETER_NAMES)])
        k = float(v[SCALE])
        n_faces = self.f.p_L.shape[0]
        # each column written where it lies: stacking them cost a copy of the whole matrix
        out: FloatArray = np.empty((n_faces + self.platter.shape[0], x.size))
        platter = out[n_faces:]
        # the platter's rows beside the faces', on another core (NumPy's loops let go of the GIL)
        side = pool("jacobian", 1).submit(self._platter_columns, x, v, H, platter)
        self._face_columns(x, v, H, out[:n_faces])
        side.result()
        if self.level_free:
            platter -= platter.mean(axis=0)
        else:
            # residuals times 1 + k: the scale error's column gains the residuals themselves
            out *= 1.0 + k
            out[:, self.free.index(SCALE)] += self(x) / (1.0 + k)
        return out

    def _face_columns(self, x: FloatArray, v: FloatArray, H: Extrinsics, out: FloatArray
                      ) -> None:
        """Into ``out`` (N, n): ∂(distance along the ray to the face)/∂x of the face returns,
        before the factor 1 + k: d(dist/a) = d dist/a − dist·a′·d cosine/a². Worked in L:
        each return's face normal is taken there (by its platter angle and H), so that the
        distance and the cosine are dot products with vectors in L."""
        f, n_free, k1 = self.f, len(self.free), 1.0 + float(v[SCALE])
        R, t = H.R, H.t
        yaw = float(x[n_free + 2])
        cy, sy = math.cos(yaw), math.sin(yaw)
        side = f.side.astype(np.float64)
        ny, nz = side_normals(f, cy, sy)
        normal = np.column_stack([1.0 - side, side * ny, side * nz])
        ny, nz = side_normals(f, -sy, cy)  # d/d yaw: the normals a quarter turn on
        turned = np.column_stack([np.zeros_like(side), side * ny, side * nz])
        centre = normal[:, 1] * x[n_free] + normal[:, 2] * x[n_free + 1]
        normal_P = unspun(normal, f.cos, f.sin)
        normal_L = normal_P @ R.T
        turned_L = unspun(turned, f.cos, f.sin) @ R.T
        cosine = rowdot(normal_L, f.rays)
        shape = incidence_shape(cosine, LEAST_COSINE_KNOWN)
        shape_slope = incidence_shape_slope(cosine, LEAST_COSINE_KNOWN)
        corrected = correct_vector(f.p_L, v, shape, self.rho)
        from_origin = corrected - t
        dist = (rowdot(normal_L, from_origin) - centre
                - np.where(f.side, 0.5 * self.edge, self.edge))
        a = away_from_grazing(cosine)
        a_slope = (np.abs(cosine) > GRAZING_FACE).astype(np.float64)

        def column(d_dist: FloatArray, d_cosine: FloatArray | float = 0.0) -> FloatArray:
            out: FloatArray = d_dist / a - dist * a_slope * d_cosine / a**2
            return out

        def moved(d_normal_L: FloatArray) -> FloatArray:
            """the column of a parameter that turns the normals in L by ``d_normal_L``: the
            distance directly, and through the incidence bias's shape along the ray"""
            d_cosine = rowdot(d_normal_L, f.rays)
            d_rho = -v[INCIDENCE] * shape_slope * d_cosine / k1
            return column(rowdot(d_normal_L, from_origin) + cosine * d_rho, d_cosine)

        for j, i in enumerate(self.free):
            if i < 3:  # tx, ty, tz
                out[:, j] = column(-normal_L[:, i])
            elif i < len(PARAMETER_NAMES):
                out[:, j] = moved(normal_P @ rotation_derivative(v[: len(PARAMETER_NAMES)], i).T)
            elif i == OFFSET:
                out[:, j] = column(-cosine / k1)
            elif i == INCIDENCE:
                out[:, j] = column(-cosine * shape / k1)
            else:  # SCALE
                out[:, j] = column(-rowdot(normal_L, corrected) / k1)
        out[:, n_free] = column(-normal[:, 1])
        out[:, n_free + 1] = column(-normal[:, 2])
        # the yaw turns the side faces' normals, and with them the centre's share
        out[:, n_free + 2] = moved(turned_L)
        out[:, n_free + 2] -= (turned[:, 1] * x[n_free] + turned[:, 2] * x[n_free + 1]) / a
        out[:, n_free + 3:] = 0.0

    def _platter_columns(self, x: FloatArray, v: FloatArray, H: Extrinsics, out: FloatArray
                         ) -> None:
        """Into ``out`` (M, n): ∂(height/a)/∂x of the platter's returns (before the level and
        1 + k): the height along the axis less the dish's, c·(r² − r_c²), each return in P."""
        n_free, k1 = len(self.free), 1.0 + float(v[SCALE])
        cy, cz = float(x[n_free]), float(x[n_free + 1])
        dish, level = self._platter_shape(x)
        R, t, w = H.R, H.t, self.platter_rays
        down = w @ R[:, 0]
        shape = incidence_shape(down, LEAST_COSINE_KNOWN)
        shape_slope = incidence_shape_slope(down, LEAST_COSINE_KNOWN)
        corrected = correct_vector(self.platter, v, shape, self.platter_rho)
        q = (corrected - t) @ R
        across = q[:, 1] ** 2 + q[:, 2] ** 2 - (cy * cy + cz * cz)
        height = q[:, 0] - dish * across - level  # the numerator of the residual
        a = away_from_grazing(down)
        a_slope = (np.abs(down) > GRAZING_FACE).astype(np.float64)
        ray = w @ R  # each return's ray in P: a range change moves it along that

        def column(dq: FloatArray, d_down: FloatArray | float = 0.0) -> FloatArray:
            d_height = dq[:, 0] - 2.0 * dish * (q[:, 1] * dq[:, 1] + q[:, 2] * dq[:, 2])
            out: FloatArray = d_height / a - height * a_slope * d_down / a**2
            return out

        for j, i in enumerate(self.free):
            if i < 3:
                out[:, j] = column(np.broadcast_to(-R[i], q.shape))
            elif i < len(PARAMETER_NAMES):
                dR = rotation_derivative(v[: len(PARAMETER_NAMES)], i)
                d_down = w @ dR[:, 0]
                d_rho = -v[INCIDENCE] * shape_slope * d_down / k1
                out[:, j] = column((corrected - t) @ dR + ray * d_rho[:, None], d_down)
            elif i == OFFSET:
                out[:, j] = column(-ray / k1)
            elif i == INCIDENCE:
                out[:, j] = column(-ray * (shape / k1)[:, None])
            else:  # SCALE
                out[:, j] = column(-(corrected @ R) / k1)
        centre = 2.0 * dish / a
        out[:, n_free] = centre * cy
        out[:, n_free + 1] = centre * cz
        out[:, n_free + 2] = 0.0
        shape_columns = [-across / a, -1.0 / a][: self.shape]
        for j, c in enumerate(shape_columns):
            out[:, n_free + 3 + j] = c


def unspun(q: FloatArray, cos: FloatArray, sin: FloatArray) -> FloatArray:
    """(N, 3) vectors in D taken into P: Rx(φ)·q (the inverse of ``cubecast._spun``)."""
    return np.column_stack([q[:, 0], cos * q[:, 1] - sin * q[:, 2],
                            sin * q[:, 1] + cos * q[:, 2]])


def side_normals(f: _Faces, c: float, s: float) -> tuple[FloatArray, FloatArray]:
    """(N,) the y and z (in D) of each face return's side-face normal for a cube at the yaw
    whose cosine and sine are ``c`` and ``s``."""
    return np.where(f.across_u, c, -s) * f.sign, np.where(f.across_u, s, c) * f.sign
