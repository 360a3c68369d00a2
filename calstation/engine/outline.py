"""Where a fixture appears in the lidar's scan plane, from a calibration H (DESIGN §2, §3).

A fixture is described as convex pieces, each a set of vertices in its own frame (x up from the
platter top, (y, z) across it): the L-target is its base plate and its wall, the spin target's
frustum is cut into triangular frusta fanned from its centroid, the platter is a many-sided
prism. A piece placed at ``(y, z)`` with ``yaw`` about +X (as the recipe gives a fixture's offset
and yaw) and turned by the platter angle φ is carried into L by
:func:`calstation.engine.frames.dynamic_to_lidar`; its section by the scan plane z_L = 0 is the
convex hull of the points where the segments between its vertices cross the plane.

:func:`scan_outline` gives the sections as closed polylines (x_L, y_L) in metres: what the live
line plot draws under the lidar's returns. With the true H the returns of the fixture's sides
that face the lidar lie on these outlines (to the range noise).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

from calstation.engine.frames import Extrinsics, FloatArray, dynamic_to_lidar, rot_x
from calstation.engine.settings import LTargetGeometry

PLATTER_SIDES = 96
"""Sides of the prism that stands for the platter disk."""


def box(lo: Sequence[float], hi: Sequence[float]) -> FloatArray:
    """The 8 corners of the axis-aligned box ``lo``..``hi``, (8, 3)."""
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                     for z in (lo[2], hi[2])], dtype=np.float64)


def l_target_pieces(target: LTargetGeometry) -> list[FloatArray]:
    """The L-target's base plate and wall, in its own frame: B, the corner of the base top and
    the wall's front face, at (base_thickness, 0, 0); the base plate runs toward the lidar
    (−y) for ``base_length``; the wall's top is ``h_tall`` above the base top at z = −width/2
    and ``h_short`` at +width/2 (DESIGN §3)."""
    bt, wt, half = target.base_thickness, target.wall_thickness, 0.5 * target.width
    base = box((0.0, -target.base_length, -half), (bt, wt, half))
    wall = np.array([[x, y, z]
                     for z, h in ((-half, target.h_tall), (half, target.h_short))
                     for y in (0.0, wt) for x in (bt, bt + h)], dtype=np.float64)
    return [base, wall]


def cube_pieces(edge: float) -> list[FloatArray]:
    """A cube of edge ``edge`` standing on the platter: x ∈ [0, edge], y, z ∈ [−edge/2,
    edge/2]."""
    h = 0.5 * edge
    return [box((0.0, -h, -h), (edge, h, h))]


def platter_pieces(radius: float, thickness: float, sides: int = PLATTER_SIDES
                   ) -> list[FloatArray]:
    """The platter: a disk of ``radius`` whose top is x = 0, ``thickness`` deep."""
    a = np.linspace(0.0, 2.0 * np.pi, sides, endpoint=False)
    ring = np.column_stack([radius * np.cos(a), radius * np.sin(a)])
    return [np.vstack([np.column_stack([np.full(sides, x), ring]) for x in (-thickness, 0.0)])]


def frustum_top_scale(polygon: ArrayLike, height: float, slope_deg: float) -> float:
    """Scale of a frustum's top face about its base's centroid such that its facets slope
    ≈ ``slope_deg``: the median distance d of the edge lines from the centroid is inset by
    ``height / tan(slope)``; ≤ 0.02 means the polygon is too small for that height."""
    poly = np.asarray(polygon, dtype=np.float64)
    c = polygon_centroid(poly)
    edge = np.roll(poly, -1, axis=0) - poly
    normal = np.column_stack([edge[:, 1], -edge[:, 0]]) / np.linalg.norm(edge, axis=1)[:, None]
    dist = np.abs(((poly - c) * normal).sum(axis=1))
    return 1.0 - height / math.tan(math.radians(slope_deg)) / float(np.median(dist))


def polygon_centroid(polygon: ArrayLike) -> FloatArray:
    """The area centroid of a simple polygon (N, 2)."""
    p = np.asarray(polygon, dtype=np.float64)
    q = np.roll(p, -1, axis=0)
    cross = p[:, 0] * q[:, 1] - q[:, 0] * p[:, 1]
    area = 0.5 * float(cross.sum())
    return np.array([((p[:, 0] + q[:, 0]) * cross).sum(),
                     ((p[:, 1] + q[:, 1]) * cross).sum()]) / (6.0 * area)


def frustum_pieces(polygon: ArrayLike, height: float, top_scale: float) -> list[FloatArray]:
    """A frustum on the polygon (N, 2) of (y, z), its top the base scaled by ``top_scale``
    about the centroid and lifted by ``height``, as N triangular frusta fanned from the
    centroid (convex each, for a polygon star-shaped from its centroid)."""
    poly = np.asarray(polygon, dtype=np.float64)
    c = polygon_centroid(poly)
    top = c + top_scale * (poly - c)
    pieces = []
    for i in range(poly.shape[0]):
        j = (i + 1) % poly.shape[0]
        bottom = np.array([c, poly[i], poly[j]])
        upper = np.array([c, top[i], top[j]])
        pieces.append(np.vstack([np.column_stack([np.zeros(3), bottom]),
                                 np.column_stack([np.full(3, height), upper])]))
    return pieces


def placed(pieces: Sequence[ArrayLike], y: float, z: float, yaw_rad: float = 0.0
           ) -> list[FloatArray]:
    """``pieces`` turned by ``yaw_rad`` about +X, then moved by (0, y, z)."""
    R, shift = rot_x(yaw_rad), np.array([0.0, y, z])
    return [np.asarray(p, dtype=np.float64) @ R.T + shift for p in pieces]


def plane_section(vertices_L: ArrayLike, eps: float = 1e-12) -> FloatArray:
    """The section of the convex hull of ``vertices_L`` (N, 3) by the scan plane z_L = 0: its
    corners (K, 2) of (x_L, y_L) counter-clockwise, (0, 2) when the plane misses it."""
    v = np.asarray(vertices_L, dtype=np.float64)
    z = v[:, 2]
    on = np.abs(z) <= eps
    points = [v[on, :2]]
    below, above = np.flatnonzero(z < -eps), np.flatnonzero(z > eps)
    if below.size and above.size:
        grid_a, grid_b = np.meshgrid(below, above, indexing="ij")
        a, b = grid_a.ravel(), grid_b.ravel()
        t = z[a] / (z[a] - z[b])
        points.append(v[a, :2] + t[:, None] * (v[b, :2] - v[a, :2]))
    p = np.vstack(points)
    if p.shape[0] < 2:
        return np.zeros((0, 2))
    return _hull(p)


def _hull(p: FloatArray) -> FloatArray:
    """Convex hull of 2D points, counter-clockwise (monotone chain); collinear points give the
    segment's two ends."""
    pts = sorted({(round(float(x), 12), round(float(y), 12)) for x, y in p})
    if len(pts) < 3:
        return np.asarray(pts, dtype=np.float64).reshape(-1, 2)

    def chain(seq: list[tuple[float, float]]) -> list[tuple[float, float]]:
        out: list[tuple[float, float]] = []
        for q in seq:
            while len(out) >= 2 and ((out[-1][0] - out[-2][0]) * (q[1] - out[-2][1])
                                     - (out[-1][1] - out[-2][1]) * (q[0] - out[-2][0])) <= 0:
                out.pop()
            out.append(q)
        return out

    lower, upper = chain(pts), chain(pts[::-1])
    return np.asarray(lower[:-1] + upper[:-1], dtype=np.float64)


def scan_outline(pieces: Sequence[ArrayLike], H: Extrinsics, phi: float = 0.0
                 ) -> list[FloatArray]:
    """The sections by the scan plane of ``pieces`` (vertices in P at the platter angle where
    they were placed) after the platter turned by ``phi`` (rad), under H: closed polylines
    (K + 1, 2) of (x_L, y_L) in metres, one per piece the plane cuts."""
    out = []
    for piece in pieces:
        section = plane_section(dynamic_to_lidar(np.asarray(piece, dtype=np.float64), phi, H))
        if section.shape[0] >= 2:
            out.append(np.vstack([section, section[:1]]))
    return out


def distance_to_outline(points: ArrayLike, outline: Sequence[ArrayLike]) -> FloatArray:
    """Distance (m) of each 2D point (N, 2) to the nearest segment of the polylines
    ``outline`` (inf without any)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    best = np.full(p.shape[0], np.inf)
    for line in outline:
        q = np.asarray(line, dtype=np.float64)
        for a, b in itertools.pairwise(q):
            d = b - a
            length2 = float(d @ d)
            t = np.zeros(p.shape[0]) if length2 == 0 else np.clip((p - a) @ d / length2, 0, 1)
            best = np.minimum(best, np.linalg.norm(p - (a + t[:, None] * d), axis=1))
    return best
