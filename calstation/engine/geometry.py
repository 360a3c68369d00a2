"""Point-cloud geometry shared by the shape strategy and the cube check.

Segmentation above the platter, outlier removal, the largest cluster, bounding boxes (Open3D's
minimum-volume box and calstation's upright box), face labels and plane fits. Points are (N, 3)
arrays in frame D (metres) unless a docstring says otherwise; X_D is the rotation axis, up.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

# imported with the engine, not at the first cube check (~0.05 s of the operator's wait)
from scipy import ndimage
from scipy.spatial import cKDTree

from calstation.engine.frames import FloatArray, rowdot
from calstation.errors import FineTuningError, VerificationError


def segment_above_platter(
    p_D: FloatArray, *, margin: float, radius: float, height: float
) -> NDArray[np.bool_]:
    """(N,) mask of points above the platter: margin < x_D < height, inside ``radius`` of the
    axis (metres). Frame D and P share X, so this is the paper's threshold along X_P."""
    r = np.hypot(p_D[:, 1], p_D[:, 2])
    out: NDArray[np.bool_] = (p_D[:, 0] > margin) & (p_D[:, 0] < height) & (r < radius)
    return out


def radius_outlier_mask(points: FloatArray, radius: float, neighbours: int) -> NDArray[np.bool_]:
    """(N,) True for points with at least ``neighbours`` other points within ``radius`` (m)."""
    if neighbours <= 0 or points.shape[0] == 0:
        return np.ones(points.shape[0], dtype=bool)
    if points.shape[0] <= neighbours:
        return np.zeros(points.shape[0], dtype=bool)
    return neighbours_within(points, neighbours, radius)


def largest_cluster(points: FloatArray, voxel: float = 0.005) -> NDArray[np.bool_]:
    """(N,) mask of the points in the largest 26-connected cluster of occupied ``voxel`` cells.

    Mixed pixels and spray that survive the radius filter in small dense clumps are cut off
    from the object; they would otherwise stretch a bounding box.
    """
    if points.shape[0] == 0:
        return np.zeros(0, dtype=bool)
    ijk = np.floor((points - points.min(axis=0)) / voxel).astype(np.int64)
    shape = tuple(int(v) + 1 for v in ijk.max(axis=0))
    if int(np.prod(shape)) > 50_000_000:
        return np.ones(points.shape[0], dtype=bool)
    grid = np.zeros(shape, dtype=bool)
    grid[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    labels, n = ndimage.label(grid, structure=np.ones((3, 3, 3), dtype=bool))
    if n <= 1:
        return np.ones(points.shape[0], dtype=bool)
    lab = labels[ijk[:, 0], ijk[:, 1], ijk[:, 2]]
    counts = np.bincount(lab)
    counts[0] = 0
    out: NDArray[np.bool_] = lab == int(np.argmax(counts))
    return out


def minimal_obb(points: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The minimum-volume oriented box: (centre (3,), axes (3, 3) as columns, extents (3,)).

    Open3D's (``create_from_points_minimal``), unless what it returns is not a box: axes that
    are not orthonormal (Open3D then warns "Invalid oriented bounding box", and its extents
    mean nothing). The upright box around every point (:func:`upright_box`, not robust) stands
    in for it then: the cube's, within the calibration's tilt of the smallest."""
    import open3d as o3d

    if points.shape[0] < 8:
        raise FineTuningError(f"a bounding box needs at least 8 points, got {points.shape[0]}")
    pc = o3d.utility.Vector3dVector(np.ascontiguousarray(points, dtype=np.float64))
    try:
        box = o3d.geometry.OrientedBoundingBox.create_from_points_minimal(pc, robust=True)
    except RuntimeError as exc:
        raise FineTuningError(f"the minimal bounding box failed: {exc}") from None
    axes = np.asarray(box.R).copy()
    if not np.allclose(axes.T @ axes, np.eye(3), atol=1e-6):
        return upright_box(points, robust=False)
    return np.asarray(box.center).copy(), axes, np.asarray(box.extent).copy()


def upright_box(
    points: FloatArray, robust: bool = True, strays: bool = False
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The minimum-area box standing on the platter: one axis is X_D, the footprint is the
    minimum-area rectangle of the points projected on the platter plane (rotating calipers on
    the convex hull). Returns (centre (3,), axes (3, 3) as columns, extents (3,)), metres.

    An object resting on the platter has an upright box; unlike a free box it cannot tilt to
    absorb a calibration error, so the cost stays sensitive to ry and smoother. ``robust``: the
    faces where their returns are (:func:`_robust_faces`); ``strays`` too: a few stray returns
    beyond a face do not stand for it (the cube check's dimensioning; the shape cost keeps the
    extremes, its landscape is tuned on them).
    """
    from scipy.spatial import ConvexHull, QhullError

    if points.shape[0] < 8:
        raise FineTuningError(f"a bounding box needs at least 8 points, got {points.shape[0]}")
    yz = _hull_candidates(points[:, 1:])
    try:
        hull = yz[ConvexHull(yz).vertices]
    except QhullError as exc:
        raise FineTuningError(f"the cube footprint is degenerate: {exc}") from None
    edges = np.roll(hull, -1, axis=0) - hull
    ang = np.unique(np.mod(np.arctan2(edges[:, 1], edges[:, 0]), np.pi / 2))
    c, s_ = np.cos(ang), np.sin(ang)
    u = hull @ np.vstack([c, s_])  # (H, A) coordinate along the edge direction
    v = hull @ np.vstack([-s_, c])
    area = (u.max(0) - u.min(0)) * (v.max(0) - v.min(0))
    k = int(np.argmin(area))
    du = np.array([0.0, c[k], s_[k]])
    dv = np.array([0.0, -s_[k], c[k]])
    axes = np.column_stack([[1.0, 0.0, 0.0], du, dv])
    local = axes.T @ points.T  # (3, N): the coordinates along the box axes, row by row
    lo, hi = local.min(axis=1), local.max(axis=1)
    if robust:
        lo, hi = _robust_faces(local, lo, hi, strays=strays)
    centre = axes @ (0.5 * (lo + hi))
    return centre, axes, hi - lo


_OCTAGON = np.array([[1, 0], [1, 1], [0, 1], [-1, 1], [-1, 0], [-1, -1], [0, -1], [1, -1]], float)


def _hull_candidates(yz: FloatArray) -> FloatArray:
    """The 2-D points that can be vertices of their convex hull (Akl–Toussaint): those not
    strictly inside the polygon of the extreme points in eight directions. The hull is the
    same; Qhull gets a few hundred points instead of thousands."""
    if yz.shape[0] < 64:
        return yz
    yz_t = np.ascontiguousarray(yz.T)  # (2, N): row-wise passes are quicker
    ext = yz[np.argmax(_OCTAGON @ yz_t, axis=1)]  # counter-clockwise around the hull
    edge = np.roll(ext, -1, axis=0) - ext
    inside = np.ones(yz.shape[0], dtype=bool)
    for (ay, az), (ey, ez) in zip(ext, edge, strict=True):
        if ey != 0.0 or ez != 0.0:  # a repeated extreme point has no edge
            inside &= ey * (yz_t[1] - az) - ez * (yz_t[0] - ay) > 0.0
    out: FloatArray = yz[~inside]
    return out if out.shape[0] >= 3 else yz


def _robust_faces(
    local: FloatArray,
    lo: FloatArray,
    hi: FloatArray,
    band: float = 0.008,
    keep_out: float = 0.01,
    strays: bool = False,
) -> tuple[FloatArray, FloatArray]:
    """Face positions as medians of the points near each face rather than the extremes;
    ``local`` (3, N) the points' coordinates along the box axes.

    The extremes of a noisy cloud lie ~3σ outside the true faces (the paper's OBB metric is
    biased for this reason). For each face, the points within ``band`` of the extreme and at
    least ``keep_out`` from the other side faces give the median position. With ``strays``, an
    extreme with fewer than :data:`FACE_POINTS` points (or :data:`FACE_SHARE` of them) within
    ``band`` is a few stray returns beyond the face: the outermost dense layer inside it stands
    for it (:func:`_dense_extreme`).
    The bottom (x) face is the segmentation cut and stays as it is.
    """
    lo, hi = lo.copy(), hi.copy()

    def _face_extreme(v: FloatArray, side: int, extreme: float) -> float:
        if not strays:
            return extreme
        near = np.count_nonzero(np.abs(v - extreme) < band)
        if near >= max(FACE_POINTS, FACE_SHARE * v.size):
            return extreme
        return _dense_extreme(v, side, band, extreme)

    below_top = local[0] < _face_extreme(local[0], 1, hi[0]) - keep_out
    for j in (1, 2):
        other = local[3 - j]
        inner = below_top & (other > lo[3 - j] + keep_out) & (other < hi[3 - j] - keep_out)
        v = local[j][inner]
        for side in (-1, 1):
            ref = _face_extreme(v, side, lo[j] if side < 0 else hi[j])
            near = v[np.abs(v - ref) < band]
            if near.size >= FACE_POINTS:
                (lo if side < 0 else hi)[j] = float(np.median(near))
    inner = np.ones(local.shape[1], dtype=bool)
    for j in (1, 2):
        inner &= (local[j] > lo[j] + keep_out) & (local[j] < hi[j] - keep_out)
    x = local[0][inner]
    top = x[x > _face_extreme(x, 1, hi[0]) - band]
    if top.size >= FACE_POINTS:
        hi[0] = float(np.median(top))
    return lo, hi


FACE_POINTS = 10
"""The fewest points within the band of a face for it to be taken from them."""
FACE_SHARE = 0.01
"""The smallest share of the points the band of a face found inside stray returns holds (a
tight cluster of a dozen strays is not a face)."""


def _dense_extreme(values: FloatArray, side: int, band: float, default: float) -> float:
    """The outermost of ``values`` on ``side`` (−1 the smallest, +1 the largest) with at least
    :data:`FACE_POINTS` values, and :data:`FACE_SHARE` of them, within ``band`` inward of it;
    ``default`` when none has."""
    v = np.sort(values if side < 0 else -values)
    least = max(FACE_POINTS, FACE_SHARE * v.size)
    if v.size < least:
        return default
    dense = np.flatnonzero(np.searchsorted(v, v + band, side="right") - np.arange(v.size)
                           >= least)
    if dense.size == 0:
        return default
    return float(v[dense[0]] if side < 0 else -v[dense[0]])


def signed_face_distances(
    points: FloatArray, centre: FloatArray, axes: FloatArray, extents: FloatArray
) -> FloatArray:
    """(N,) signed distance of each point to the nearest face of the box (positive inside)."""
    local = (points - centre) @ axes
    half = 0.5 * extents
    gaps = half - np.abs(local)  # distance to the face pair of each axis, >0 inside
    out: FloatArray = gaps[np.arange(gaps.shape[0]), np.argmin(np.abs(gaps), axis=1)]
    return out


def face_labels(
    points: FloatArray,
    centre: FloatArray,
    axes: FloatArray,
    extents: FloatArray,
    band: float = 0.006,
    keep_out: float = 0.01,
) -> NDArray[np.int64]:
    """(N,) face index of each point of a box (``2·axis + side``: 1 the top, 2–5 the sides),
    −1 for points farther than ``band`` from their nearest face, within ``keep_out`` of another
    face (edges, mixed pixels) or on the bottom (the segmentation cut)."""
    local = (points - centre) @ axes
    gaps = np.abs(0.5 * extents - np.abs(local))
    order = np.argsort(gaps, axis=1)
    rows = np.arange(points.shape[0])
    nearest = order[:, 0]
    label = (2 * nearest + (local[rows, nearest] > 0)).astype(np.int64)
    inside = np.all(np.abs(local) <= 0.5 * extents + band, axis=1)
    ok = inside & (gaps[rows, nearest] < band) & (gaps[rows, order[:, 1]] > keep_out) & (label != 0)
    return np.where(ok, label, -1)


def fit_plane(points: FloatArray, trim_sigma: float = 3.0) -> tuple[FloatArray, FloatArray, float]:
    """Plane through (N, 3) points (the smallest eigenvector of their scatter), refitted once
    without residuals beyond ``trim_sigma``·RMS: (centroid (3,), unit normal (3,), RMS of the
    kept residuals)."""
    if points.shape[0] < 3:
        raise VerificationError(f"a plane needs at least 3 points, got {points.shape[0]}")
    keep = np.ones(points.shape[0], dtype=bool)
    c = points.mean(axis=0)
    n = np.array([1.0, 0.0, 0.0])
    rms = 0.0
    for _ in range(2):
        kept = points[keep]
        c = kept.mean(axis=0)
        d = kept - c
        n = np.linalg.eigh(d.T @ d)[1][:, 0]
        res = (points - c) @ n
        rms = float(np.sqrt(np.mean(res[keep] ** 2)))
        keep = np.abs(res) <= trim_sigma * max(rms, 1e-6)
        if keep.sum() < 3:
            break
    return c, n, rms


LINE_JUMP = 10.0
"""A jump in azimuth between returns next in time (or platter angle), in median steps, that
starts another scan line (a line's own returns step by one, or a few over dropouts)."""


def line_ids(az: FloatArray) -> NDArray[np.int64]:
    """(N,) the scan line of each of the returns whose azimuths (rad) ``az`` are given in the
    order they were taken (or of platter angle): a line ends where the azimuth jumps by more
    than :data:`LINE_JUMP` median steps; every return its own line when no step is seen."""
    jumps = np.abs(np.diff(az))
    step = float(np.median(jumps)) if jumps.size else 0.0
    if step <= 0:
        return np.arange(az.shape[0], dtype=np.int64)
    out: NDArray[np.int64] = np.concatenate([[0], np.cumsum(jumps > LINE_JUMP * step)])
    return out


def whole_lines(p_L: FloatArray, most: int) -> NDArray[np.intp]:
    """Positions of at most about ``most`` of the returns ((N, 3) in L, in scan order): all of
    them, or every k-th scan line's (a line ends where the azimuth jumps back,
    :func:`line_ids`), so that a line's returns stay together."""
    if p_L.shape[0] <= most:
        return np.arange(p_L.shape[0])
    stride = -(-p_L.shape[0] // most)
    lines = line_ids(np.arctan2(p_L[:, 0], p_L[:, 1]))
    out: NDArray[np.intp] = np.flatnonzero(lines % stride == 0)
    return out


DENSITY_SAMPLE = 16_384
"""Points whose distance to their 8th neighbour sets :func:`density_outlier_mask`'s radius,
in a cloud of more than 4 times as many (every k-th in the tree's order, spread over the
cloud): the median of 18 700 of the default cube's 112 000 moved the radius by 0.06 % and kept
the same returns. A smaller cloud's radius is found from all of its points, in one search."""


def density_outlier_mask(p: FloatArray, neighbours: int = 8) -> NDArray[np.bool_]:
    """Radius outlier removal with the radius scaled to the cloud's density (3× the median
    distance to the 8th neighbour; of :data:`DENSITY_SAMPLE` of the points in a large cloud):
    (N,) True for the returns kept; isolated returns (mixed pixels, spray) go."""
    n = p.shape[0]
    if n <= neighbours + 1:
        return np.ones(n, dtype=bool)
    tree = cKDTree(p, balanced_tree=False, compact_nodes=False)
    if n <= 4 * DENSITY_SAMPLE:
        far = _kth_distance(tree, p, np.ones(n, dtype=bool), neighbours, math.inf)
        out: NDArray[np.bool_] = far <= 3.0 * float(np.median(far))
        return out
    sample = tree.indices[:: n // DENSITY_SAMPLE]
    dist, _ = tree.query(p[sample], k=neighbours + 1, workers=-1)
    return neighbours_within(p, neighbours, 3.0 * float(np.median(dist[:, -1])), tree)


def neighbours_within(
    p: FloatArray, k: int, radius: float, tree: cKDTree | None = None
) -> NDArray[np.bool_]:
    """(N,) True for the (N, 3) points with at least ``k`` others within ``radius`` (m).

    Points that share a cell of a grid of edge radius/√3 are within the radius of each other,
    so a cell of k + 1 points or more keeps all of them without a search (about half the
    returns of a cube scan at the cube check's radius); the others are searched in ``tree``
    (built on ``p`` when not given)."""
    out = _crowded_cells(p, k, radius)
    if not out.all():
        if tree is None:
            tree = cKDTree(p, balanced_tree=False, compact_nodes=False)
        out |= _kth_distance(tree, p, ~out, k, np.nextafter(radius, np.inf)) <= radius
    return out


def _kth_distance(
    tree: cKDTree, p: FloatArray, which: NDArray[np.bool_], k: int, upper: float
) -> FloatArray:
    """(N,) the distance from each of the points ``p`` marked in ``which`` to its ``k``-th
    nearest other point in ``tree`` (built on ``p``); inf where that is ``upper`` or farther,
    and where not marked. Searched in the tree's order (neighbours in memory): ~25 % quicker
    than in the cloud's."""
    order = tree.indices[which[tree.indices]]
    dist, _ = tree.query(p[order], k=k + 1, distance_upper_bound=upper, workers=-1)
    out = np.full(p.shape[0], np.inf)
    out[order] = dist[:, -1]
    return out


def _crowded_cells(p: FloatArray, k: int, radius: float) -> NDArray[np.bool_]:
    """(N,) True for the points in a cell of more than ``k`` points, the cells cubes of edge
    just under radius/√3 (their diagonal within the radius); all False for a grid too fine to
    number in 63 bits or a cloud that is not finite."""
    edge = radius / math.sqrt(3.0) * (1.0 - 1e-9)
    none = np.zeros(p.shape[0], dtype=bool)
    if not edge > 0 or p.shape[0] <= k or not np.isfinite(p).all():
        return none
    cell = ((p - p.min(axis=0)) / edge).astype(np.int64)
    dims = cell.max(axis=0) + 1
    if float(dims[0]) * float(dims[1]) * float(dims[2]) >= 2.0**62:
        return none
    key = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    out: NDArray[np.bool_] = counts[inverse.reshape(-1)] > k
    return out


VEIL_DEG = 10.0
"""A return whose segment to an adjacent return of its scan line lies within this angle of its
ray is on a veil (degrees): a mixed pixel between a depth edge's near and far surfaces, or a
surface seen this close to grazing. ROS laser_filters' shadow filter takes the same 10°."""

ADJACENT_STEPS = 2.5
"""Returns whose rays are at most this many of the scan's beam steps apart are adjacent (a
dropped return between them included)."""


def veil_mask(p_L: FloatArray, idx: NDArray[np.intp]) -> NDArray[np.bool_]:
    """(K,) True for the returns at positions ``idx`` of a scan's returns ``p_L`` ((N, 3) in L,
    the lidar at the origin, in the order taken) that lie on a veil (:data:`VEIL_DEG`) with
    the return before or after them, when it is adjacent (:data:`ADJACENT_STEPS`).

    A footprint across a depth edge returns a range between the two surfaces; over a turn such
    returns gather at an object's edges in clumps dense enough to pass a density filter, and
    they stretch a bounding box by up to the depth of the edge."""
    out = np.zeros(idx.shape[0], dtype=bool)
    if p_L.shape[0] < 2 or idx.shape[0] == 0:
        return out
    p = p_L[idx]
    pp = rowdot(p, p)
    pairs = []
    for side in (-1, 1):
        j = np.clip(idx + side, 0, p_L.shape[0] - 1)
        q = p_L[j]
        qq, pq = rowdot(q, q), rowdot(p, q)
        # the rays' angle's cosine, and (ray · (q − p))² against cos²(VEIL_DEG)·|q − p|²; a
        # return at the origin is no ray (NaN: on no veil)
        with np.errstate(divide="ignore", invalid="ignore"):
            apart = pq / np.sqrt(pp * qq)
            along = (pq - pp) ** 2 / pp
        d2 = qq - 2.0 * pq + pp
        pairs.append((apart, along > math.cos(math.radians(VEIL_DEG))**2 * d2, j != idx))
    cosines = np.concatenate([apart[real] for apart, _, real in pairs])
    cosines = cosines[np.isfinite(cosines)]
    if cosines.size == 0:
        return out
    step = math.acos(min(1.0, float(np.median(cosines))))
    least = math.cos(ADJACENT_STEPS * step)
    for apart, on_ray, real in pairs:
        out |= real & (apart >= least) & on_ray
    return out


def platter_level(p_D: FloatArray, platter_radius: float, window: float = 0.02) -> float:
    """Height (m, along X_D) of the platter top as seen in a spin scan ((N, 3) points in D).

    The median of the returns within ``window`` of x_D = 0 on the platter, refined twice to
    those within 3 mm of it (the cube's lowest returns fall in the window too; the platter's
    far outnumber them). 0 when fewer than 100 platter returns are seen.
    """
    r2 = p_D[:, 1] ** 2 + p_D[:, 2] ** 2
    x = p_D[:, 0]
    return level_of_heights(x[(np.abs(x) < window) & (r2 < (platter_radius - 0.005) ** 2)])


def level_of_heights(x: FloatArray) -> float:
    """:func:`platter_level` from the heights (m) of the returns on the platter within the
    window: their median, refined twice to those within 3 mm of it; 0 for fewer than 100."""
    if x.size < 100:
        return 0.0
    level = float(np.median(x))
    for _ in range(2):
        near = x[np.abs(x - level) < 0.003]
        if near.size < 100:
            break
        level = float(np.median(near))
    return level
