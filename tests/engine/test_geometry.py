"""The geometry helpers' shortcuts against their plain definitions."""

from __future__ import annotations

import numpy as np
from hypothesis import assume, given, settings, strategies as st
from scipy.spatial import ConvexHull, QhullError

from calstation.engine.cube import FaceFlatness
from calstation.engine.frames import Extrinsics, lidar_to_dynamic
from calstation.engine.geometry import (
    _hull_candidates,
    level_of_heights,
    platter_level,
    radius_outlier_mask,
    upright_box,
    veil_mask,
)


def _hull(points: np.ndarray) -> set[tuple[float, float]]:
    return {tuple(v) for v in points[ConvexHull(points).vertices]}


@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(64, 4000),
    angle=st.floats(0.0, 2 * np.pi),
    aspect=st.floats(0.05, 1.0),
    rounded=st.booleans(),
    seed=st.integers(0, 2**31 - 1),
)
def test_hull_candidates_keep_every_hull_vertex(
    n: int, angle: float, aspect: float, rounded: bool, seed: int
) -> None:
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-1.0, 1.0, (n, 2)) * [1.0, aspect]
    c, s = np.cos(angle), np.sin(angle)
    pts = pts @ np.array([[c, s], [-s, c]])
    if rounded:  # repeated extreme points and collinear hull edges
        pts = np.round(pts, 1)
    try:
        full = _hull(pts)
    except QhullError:  # rounding left the points on one line: no 2-D hull to compare with
        assume(False)
    kept = _hull_candidates(pts)
    assert kept.shape[0] <= pts.shape[0]
    assert _hull(kept) == full


def test_hull_candidates_drop_the_interior() -> None:
    pts = np.random.default_rng(1).normal(size=(5000, 2))
    assert _hull_candidates(pts).shape[0] < 500


def test_upright_box_of_a_rotated_cube() -> None:
    rng = np.random.default_rng(2)
    # returns on the four sides and the top of a 0.1 m cube turned by 0.3 rad about X
    u = rng.uniform(-0.05, 0.05, 20000)
    h = rng.uniform(0.0, 0.1, 20000)
    side = rng.integers(0, 5, 20000)
    local = np.column_stack([h, u, np.full_like(u, 0.05)])
    local[side == 1, 2] = -0.05
    local[side == 2] = np.column_stack([h, np.full_like(u, 0.05), u])[side == 2]
    local[side == 3] = np.column_stack([h, np.full_like(u, -0.05), u])[side == 3]
    local[side == 4] = np.column_stack([np.full_like(u, 0.1), u, rng.uniform(-0.05, 0.05, 20000)])[
        side == 4
    ]
    local += rng.normal(0.0, 0.0005, local.shape)
    c, s = np.cos(0.3), np.sin(0.3)
    pts = local @ np.array([[1, 0, 0], [0, c, s], [0, -s, c]]) + [0.0, 0.2, -0.1]
    centre, axes, extents = upright_box(pts)
    assert np.allclose(np.sort(extents[1:]), [0.1, 0.1], atol=3e-4)
    assert abs(extents[0] - 0.1) < 1e-3
    assert abs(abs(axes[1, 1]) - c) < 1e-3 or abs(abs(axes[1, 1]) - s) < 1e-3
    assert np.allclose(centre[1:], [0.2, -0.1], atol=3e-4)
    # a few stray returns 11 mm beyond a side and above the top (mixed pixels at the edges):
    # the faces stay where the returns are
    for strays in (1, 5, 9):
        extra = np.column_stack([np.full(strays, 0.05), np.full(strays, 0.061),
                                 np.linspace(-0.03, 0.03, strays)])
        top = np.column_stack([np.full(strays, 0.111), np.linspace(-0.03, 0.03, strays),
                               np.zeros(strays)])
        more = np.vstack([local, extra, top]) @ np.array([[1, 0, 0], [0, c, s], [0, -s, c]])
        _, _, ext2 = upright_box(more + np.array([0.0, 0.2, -0.1]), strays=True)
        assert np.allclose(np.sort(ext2[1:]), [0.1, 0.1], atol=3e-4), (strays, ext2)
        assert abs(ext2[0] - 0.1) < 1e-3, (strays, ext2)


def test_platter_level_from_height_and_radius_alone() -> None:
    rng = np.random.default_rng(3)
    n = 50000
    r = np.sqrt(rng.uniform(0.0, 0.15**2, n))
    a = rng.uniform(0.0, 2 * np.pi, n)
    x = rng.normal(0.002, 0.0005, n)
    x[:2000] = rng.uniform(0.0, 0.1, 2000)  # a cube's returns above it
    p_D = np.column_stack([x, r * np.cos(a), r * np.sin(a)])
    level = platter_level(p_D, 0.15)
    assert abs(level - 0.002) < 2e-5
    on_platter = (np.abs(x) < 0.02) & (r < 0.145)
    assert level == level_of_heights(x[on_platter])


def test_face_flatness_is_the_plane_fit_residual() -> None:
    rng = np.random.default_rng(4)
    H = Extrinsics(tx=0.01, ty=1.2, tz=-0.02, rx=0.0, ry=0.01, rz=-0.8)
    faces_L, faces_phi = [], []
    for _ in range(3):
        pts = rng.normal(size=(500, 3)) * [0.3, 0.3, 0.0]
        faces_L.append(pts)
        faces_phi.append(rng.uniform(0.0, 2 * np.pi, 500))
    got = FaceFlatness(faces_L, faces_phi)(H)
    start = 0
    for p, f in zip(faces_L, faces_phi, strict=True):
        q = lidar_to_dynamic(p, f, H)
        d = q - q.mean(axis=0)
        want = d @ np.linalg.svd(d, full_matrices=False)[2][2]
        part = got[start : start + p.shape[0]]
        assert np.allclose(np.abs(part), np.abs(want), atol=1e-12)
        assert np.allclose(part, want, atol=1e-12) or np.allclose(part, -want, atol=1e-12)
        start += p.shape[0]


@settings(max_examples=30, deadline=None)
@given(
    n=st.integers(20, 600),
    radius=st.floats(0.01, 0.3),
    neighbours=st.integers(1, 10),
    seed=st.integers(0, 2**31 - 1),
)
def test_radius_outlier_mask_counts_neighbours_within_the_radius(
    n: int, radius: float, neighbours: int, seed: int
) -> None:
    rng = np.random.default_rng(seed)
    pts = np.concatenate([rng.normal(0.0, 0.05, (n, 3)), rng.uniform(-1.0, 1.0, (n // 10, 3))])
    d = np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=2)
    others = (d <= radius).sum(axis=1) - 1
    assert np.array_equal(radius_outlier_mask(pts, radius, neighbours), others >= neighbours)


def _line_on(distance: np.ndarray, az: np.ndarray) -> np.ndarray:
    """A scan line's returns in L at ``distance`` (m) along azimuths ``az`` (rad)."""
    return np.column_stack([distance * np.sin(az), distance * np.cos(az), np.zeros(az.size)])


def test_veil_mask_marks_the_returns_between_a_depth_edges_surfaces() -> None:
    """A wall 1 m away for half the line and one 1.3 m away for the rest, with a return half-way
    between them at the edge (a mixed pixel), the return before it dropped: the mixed pixel and
    the returns either side of it are on the veil (the one before the dropped return is still
    adjacent), the walls' other returns are not; nor are the returns where the next line, at
    another range, begins."""
    az = np.radians(np.linspace(-10.0, 10.0, 401))
    rho = np.where(az < 0, 1.0, 1.3)
    edge = int(np.argmax(az >= 0))
    rho[edge] = 1.15
    keep = np.ones(az.size, dtype=bool)
    keep[edge - 1] = False
    first = _line_on(rho[keep], az[keep])
    p_L = np.vstack([first, _line_on(np.full(az.size, 2.0), az)])
    marked = np.flatnonzero(veil_mask(p_L, np.arange(p_L.shape[0])))
    at = edge - 1  # the mixed pixel's position among the kept returns
    assert set(marked) == {at - 1, at, at + 1}, marked


def test_veil_mask_marks_a_surface_only_near_grazing() -> None:
    """A flat wall seen at 60° of incidence is no veil; the same wall at 85° is."""
    az = np.radians(np.linspace(-2.0, 2.0, 81))
    for incidence, veiled in ((60.0, False), (85.0, True)):
        # the wall's normal at `incidence` from the ray at az = 0, in the scan plane
        n = np.array([np.sin(np.radians(incidence)), np.cos(np.radians(incidence)), 0.0])
        rays = _line_on(np.ones(az.size), az)
        p_L = rays * (1.0 / (rays @ n))[:, None]
        mask = veil_mask(p_L, np.arange(az.size))
        assert mask.all() if veiled else not mask.any(), (incidence, mask.sum())


def test_density_outlier_mask_of_a_large_cloud_is_the_one_of_every_point() -> None:
    """Beyond 4 × ``DENSITY_SAMPLE`` points the radius comes from a sample and crowded grid
    cells keep their points without a search: the same returns kept as by every point's own
    distance to its 8th neighbour, the strays dropped."""
    from scipy.spatial import cKDTree

    from calstation.engine import geometry

    rng = np.random.default_rng(5)
    n = 5 * geometry.DENSITY_SAMPLE
    face = np.column_stack([rng.uniform(0, 0.3, n), rng.uniform(0, 0.3, n),
                            rng.normal(0, 0.0005, n)])
    strays = rng.uniform(-0.5, 0.8, (300, 3))
    p = np.concatenate([face, strays])
    far = cKDTree(p).query(p, k=9)[0][:, -1]
    radius = 3.0 * float(np.median(far))
    keep = geometry.density_outlier_mask(p)
    assert np.array_equal(keep, far <= radius)
    assert keep[:n].all() and keep[n:].mean() < 0.05
    # the grid did keep most of the face without a search
    assert geometry._crowded_cells(p, 8, radius)[:n].mean() > 0.2


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), k=st.integers(1, 10), scale=st.floats(0.6, 1.6))
def test_neighbours_within_counts_as_a_search_of_every_point(seed: int, k: int,
                                                             scale: float) -> None:
    """Crowded grid cells keep their points without a search, and only when every point of
    the cell is within the radius: at a density where a point has about ``k`` neighbours
    within the radius, the counts of a search of every point decide the same."""
    from scipy.spatial import cKDTree

    from calstation.engine.geometry import neighbours_within

    n = 8000
    p = np.random.default_rng(seed).uniform(0.0, 1.0, (n, 3))
    radius = scale * (3.0 * k / (4.0 * np.pi * n)) ** (1.0 / 3.0)
    others = cKDTree(p).query_ball_point(p, radius, return_length=True) - 1
    assert np.array_equal(neighbours_within(p, k, radius), others >= k)
