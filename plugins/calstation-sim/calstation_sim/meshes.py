"""Fixture meshes built from recipe geometry (DESIGN §3), in the fixture's own frame.

Every builder returns an Open3D :class:`open3d.geometry.TriangleMesh` in metres, in a frame aligned
with D (+X up out of the platter, the platter top at x = 0). The fixture's reference point (the
L-target's B, the frustum's polygon origin, the cube/pyramid/prism centre line) sits on the X
axis, so :func:`place_mesh` only has to turn it about +X (yaw) and move it along Y/Z (offset).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from calstation.engine import outline
from calstation.errors import SimulationError
from calstation.recipes import (
    CubeGeometry,
    FrustumGeometry,
    LoadedRecipe,
    LTargetGeometry,
    MeshGeometry,
    PlatterGeometry,
    PrismGeometry,
    PyramidGeometry,
)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int32]

PLATTER_SEGMENTS = 512
"""Polygon segments of the platter disk (sagitta ≈ 22 µm on a 585 mm platter)."""


def to_mesh(vertices: FloatArray, triangles: NDArray[np.integer]) -> o3d.geometry.TriangleMesh:
    """An Open3D mesh from (V, 3) vertices (m) and (F, 3) vertex indices."""
    mesh = o3d.geometry.TriangleMesh()
    mesh.vertices = o3d.utility.Vector3dVector(np.asarray(vertices, dtype=np.float64))
    mesh.triangles = o3d.utility.Vector3iVector(np.asarray(triangles, dtype=np.int32))
    return mesh


def mesh_arrays(mesh: o3d.geometry.TriangleMesh) -> tuple[FloatArray, IntArray]:
    """(V, 3) vertices (m) and (F, 3) triangles of an Open3D mesh."""
    return (
        np.asarray(mesh.vertices, dtype=np.float64),
        np.asarray(mesh.triangles, dtype=np.int32),
    )


def _hexahedron(corners: FloatArray) -> tuple[FloatArray, IntArray]:
    """A closed six-faced solid from 8 corners ordered as a box's (i, j, k) ∈ {0,1}³ with
    index ``i + 2j + 4k``; faces need not be rectangles (the L-target wall's top is sloped)."""
    quads = [
        (0, 2, 6, 4),  # i = 0
        (1, 5, 7, 3),  # i = 1
        (0, 4, 5, 1),  # j = 0
        (2, 3, 7, 6),  # j = 1
        (0, 1, 3, 2),  # k = 0
        (4, 6, 7, 5),  # k = 1
    ]
    tris = []
    for a, b, c, d in quads:
        tris += [(a, b, c), (a, c, d)]
    return np.asarray(corners, dtype=np.float64), np.asarray(tris, dtype=np.int32)


def _box(
    lo: tuple[float, float, float], hi: tuple[float, float, float]
) -> tuple[FloatArray, IntArray]:
    corners = np.array(
        [
            [(lo, hi)[i][0], (lo, hi)[j][1], (lo, hi)[k][2]]
            for k in (0, 1)
            for j in (0, 1)
            for i in (0, 1)
        ]
    )
    return _hexahedron(corners)


def _merge(*parts: tuple[FloatArray, IntArray]) -> tuple[FloatArray, IntArray]:
    verts, tris, n = [], [], 0
    for v, t in parts:
        verts.append(v)
        tris.append(t + n)
        n += len(v)
    return np.vstack(verts), np.vstack(tris).astype(np.int32)


def _prism(
    outline_yz: FloatArray, x0: float, x1: float, top_yz: FloatArray | None = None
) -> tuple[FloatArray, IntArray]:
    """A closed solid between polygon ``outline_yz`` at x0 and ``top_yz`` (same vertex count;
    default the same outline) at x1; the caps are fan-triangulated from their centroids."""
    base = np.asarray(outline_yz, dtype=np.float64)
    top = base if top_yz is None else np.asarray(top_yz, dtype=np.float64)
    n = len(base)
    cb, ct = polygon_centroid(base), polygon_centroid(top)
    verts = np.vstack(
        [
            np.column_stack([np.full(n, x0), base]),
            np.column_stack([np.full(n, x1), top]),
            [[x0, cb[0], cb[1]], [x1, ct[0], ct[1]]],
        ]
    )
    tris: list[tuple[int, int, int]] = []
    for i in range(n):
        j = (i + 1) % n
        tris += [(i, j, n + j), (i, n + j, n + i)]  # side facet
        tris.append((2 * n, j, i))  # bottom cap
        tris.append((2 * n + 1, n + i, n + j))  # top cap
    return verts, np.asarray(tris, dtype=np.int32)


def polygon_centroid(poly: FloatArray) -> FloatArray:
    """Area centroid (2,) of a simple polygon given as (N, 2) vertices."""
    p = np.asarray(poly, dtype=np.float64)
    q = np.roll(p, -1, axis=0)
    cross = p[:, 0] * q[:, 1] - q[:, 0] * p[:, 1]
    area = 0.5 * cross.sum()
    if abs(area) < 1e-12:
        raise SimulationError("frustum polygon has zero area")
    c = ((p + q) * cross[:, None]).sum(axis=0) / (6.0 * area)
    return np.asarray(c, dtype=np.float64)


def polygon_area(poly: FloatArray) -> float:
    """Signed area of a polygon (positive when counter-clockwise in (y, z))."""
    p = np.asarray(poly, dtype=np.float64)
    q = np.roll(p, -1, axis=0)
    return float(0.5 * (p[:, 0] * q[:, 1] - q[:, 0] * p[:, 1]).sum())


# --- fixtures -------------------------------------------------------------------------------
PLATTER_RINGS = 24
"""Rings of the top surface of a platter that is not flat (its dish is sampled radially)."""


def platter_mesh(
    geom: PlatterGeometry, segments: int = PLATTER_SEGMENTS, flatness: float = 0.0
) -> o3d.geometry.TriangleMesh:
    """The platter disk in frame D: top surface at x = 0, bottom at x = −thickness.

    ``flatness`` (m, peak to valley): the top is a shallow dish
    x = (flatness/2)·(2·(r/R)² − 1) instead (the rim higher than the centre when positive),
    whose mean over the top's area is 0."""
    a = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    r = 0.5 * geom.diameter
    outline = np.column_stack([r * np.cos(a), r * np.sin(a)])
    if flatness == 0.0:
        return to_mesh(*_prism(outline, -geom.thickness, 0.0))
    return to_mesh(*_dished_disk(outline, r, -geom.thickness, flatness))


def _dished_disk(
    outline_yz: FloatArray, radius: float, x0: float, flatness: float
) -> tuple[FloatArray, IntArray]:
    """The platter of :func:`platter_mesh` with a dished top: the side and bottom as a prism's,
    the top triangulated over :data:`PLATTER_RINGS` rings."""
    n = len(outline_yz)

    def height(frac: float) -> float:
        return 0.5 * flatness * (2.0 * frac**2 - 1.0)

    rings = np.linspace(0.0, 1.0, PLATTER_RINGS + 1)[1:]
    verts = [[x0, 0.0, 0.0], [height(0.0), 0.0, 0.0]]  # bottom centre, top centre
    verts += [[x0, *p] for p in outline_yz]  # bottom rim: 2 … n+1
    for f in rings:  # top rings: ring k at 2 + n·(k+1)
        verts += [[height(f), *(f * p)] for p in outline_yz]
    tris: list[tuple[int, int, int]] = []
    bottom, top_rim = 2, 2 + n * PLATTER_RINGS
    for i in range(n):
        j = (i + 1) % n
        tris.append((0, bottom + j, bottom + i))  # bottom cap
        tris += [(bottom + i, bottom + j, top_rim + j), (bottom + i, top_rim + j, top_rim + i)]
        tris.append((1, 2 + n + i, 2 + n + j))  # the top's centre fan
        for k in range(1, PLATTER_RINGS):
            inner, outer = 2 + n * k, 2 + n * (k + 1)
            tris += [(inner + i, outer + i, outer + j), (inner + i, outer + j, inner + j)]
    return np.asarray(verts, dtype=np.float64), np.asarray(tris, dtype=np.int32)


def wall_height(geom: LTargetGeometry, z: float | FloatArray) -> float | FloatArray:
    """Height (m) of the L-target's wall above the base top at z_P = ``z`` (local frame)."""
    return geom.h_mid - (geom.h_tall - geom.h_short) * np.asarray(z) / geom.width


def l_target_mesh(geom: LTargetGeometry) -> o3d.geometry.TriangleMesh:
    """The static L-target (DESIGN §3) with B at (base_thickness, 0, 0).

    The base plate spans y ∈ [−base_length, wall_thickness] (A at y = −base_length, toward the
    lidar), x ∈ [0, base_thickness]; the wall's front face is the plane y = 0, its back face
    y = wall_thickness, and its top is ``h_tall`` above the base top at z = −width/2 and
    ``h_short`` at z = +width/2.
    """
    bt, wt, w = geom.base_thickness, geom.wall_thickness, geom.width
    base = _box((0.0, -geom.base_length, -w / 2), (bt, wt, w / 2))
    corners = []
    for k in (0, 1):
        z = -w / 2 if k == 0 else w / 2
        top = bt + float(wall_height(geom, z))
        for j in (0, 1):
            y = 0.0 if j == 0 else wt
            for i in (0, 1):
                corners.append([bt if i == 0 else top, y, z])
    wall = _hexahedron(np.asarray(corners))
    return to_mesh(*_merge(base, wall))


def frustum_polygon(geom: FrustumGeometry) -> FloatArray:
    """The base outline (N, 2) in (y, z), counter-clockwise: the recipe's polygon, or the
    regular heptagon of ``circumradius`` with vertex 0 pulled in by ``notch_depth``."""
    if geom.polygon is not None:
        poly = np.asarray(geom.polygon, dtype=np.float64)
    else:
        a = 2.0 * np.pi * np.arange(7) / 7
        r = np.full(7, geom.circumradius)
        r[0] *= 1.0 - geom.notch_depth
        poly = np.column_stack([r * np.cos(a), r * np.sin(a)])
    area = polygon_area(poly)
    if abs(area) < 1e-9:
        raise SimulationError("fixtures.spin_target.polygon: the polygon has zero area")
    return poly if area > 0 else poly[::-1].copy()


def frustum_top_scale(geom: FrustumGeometry, poly: FloatArray) -> float:
    """Scale of the top face about the centroid so the facets slope ≈ ``slope_deg``
    (:func:`calstation.engine.outline.frustum_top_scale`, which the live outline uses too)."""
    scale = outline.frustum_top_scale(poly, geom.height, geom.slope_deg)
    if scale <= 0.02:
        inset = geom.height / math.tan(math.radians(geom.slope_deg))
        raise SimulationError(
            f"fixtures.spin_target: height {geom.height} m at slope {geom.slope_deg}° needs an "
            f"inset of {inset:.3f} m, more than the polygon allows (scale of its top "
            f"{scale:.3f}); lower the height or raise slope_deg"
        )
    return scale


def frustum_mesh(geom: FrustumGeometry) -> o3d.geometry.TriangleMesh:
    """The spin target: a polygonal frustum on x = 0, top face at x = ``height``.

    The top is the base scaled about the polygon centroid (:func:`frustum_top_scale`); caps are
    fan-triangulated from the centroid, so the polygon must be star-shaped from it.
    """
    poly = frustum_polygon(geom)
    c = polygon_centroid(poly)
    rel = poly - c
    q = np.roll(rel, -1, axis=0)
    if np.any(rel[:, 0] * q[:, 1] - rel[:, 1] * q[:, 0] <= 0):
        raise SimulationError(
            "fixtures.spin_target.polygon: the polygon is not star-shaped from its centroid "
            "(fan triangulation needs every vertex visible from the centroid)"
        )
    scale = frustum_top_scale(geom, poly)
    return to_mesh(*_prism(poly, 0.0, geom.height, c + scale * rel))


def cube_mesh(geom: CubeGeometry) -> o3d.geometry.TriangleMesh:
    """A cube of edge s: x ∈ [0, s], y, z ∈ [−s/2, s/2]."""
    s = geom.edge
    return to_mesh(*_box((0.0, -s / 2, -s / 2), (s, s / 2, s / 2)))


def pyramid_mesh(geom: PyramidGeometry) -> o3d.geometry.TriangleMesh:
    """A square pyramid: base side b centred on the X axis at x = 0, apex at x = height."""
    h = geom.base / 2
    verts = np.array(
        [[0, -h, -h], [0, h, -h], [0, h, h], [0, -h, h], [geom.height, 0, 0]], dtype=np.float64
    )
    tris = np.array([[0, 2, 1], [0, 3, 2], [0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
    return to_mesh(verts, tris)


def prism_mesh(geom: PrismGeometry) -> o3d.geometry.TriangleMesh:
    """A triangular prism lying on a rectangular face: an equilateral triangle of ``edge`` in
    the (y, x) plane (base on x = 0, apex at x = edge·√3/2), extruded along Z over ``depth``."""
    e, d = geom.edge, geom.depth
    tri_yx = np.array([[-e / 2, 0.0], [e / 2, 0.0], [0.0, e * math.sqrt(3) / 2]])
    # _prism extrudes along X; build along X then swap X and Z.
    verts, tris = _prism(tri_yx, -d / 2, d / 2)
    zyx = verts[:, [2, 1, 0]]  # (x', y', z') = (x_tri, y_tri, extrusion)
    return to_mesh(zyx, tris[:, ::-1])  # swapping axes mirrors: flip the winding


def load_mesh_file(path: Path, field: str) -> o3d.geometry.TriangleMesh:
    """A fixture mesh from an STL/PLY/OBJ file (metres, frame D: +X up from the platter top)."""
    if not path.is_file():
        raise SimulationError(f"{field}: mesh file not found: {path}")
    if path.suffix.lower() not in {".stl", ".ply", ".obj"}:
        raise SimulationError(f"{field}: {path} is not an STL, PLY or OBJ mesh")
    mesh = o3d.io.read_triangle_mesh(path)
    if len(mesh.triangles) == 0 or len(mesh.vertices) == 0:
        raise SimulationError(f"{field}: mesh file {path} holds no triangles")
    v = np.asarray(mesh.vertices)
    if not np.isfinite(v).all():
        raise SimulationError(f"{field}: mesh file {path} has non-finite vertices")
    return mesh


Geometry = (
    LTargetGeometry
    | FrustumGeometry
    | CubeGeometry
    | PyramidGeometry
    | PrismGeometry
    | MeshGeometry
)


def fixture_mesh(
    geom: Geometry, recipe: LoadedRecipe | None = None, field: str = "fixture"
) -> o3d.geometry.TriangleMesh:
    """The mesh of any recipe fixture in its own frame (a named mesh file wins over geometry).

    Relative mesh paths resolve against the recipe file's folder. ``field`` names the recipe
    field in error messages (e.g. ``fixtures.spin_target``).
    """
    mesh_name = getattr(geom, "mesh", None)
    if mesh_name:
        path = recipe.resolve(mesh_name) if recipe is not None else Path(mesh_name)
        return load_mesh_file(path, f"{field}.mesh")
    if isinstance(geom, LTargetGeometry):
        return l_target_mesh(geom)
    if isinstance(geom, FrustumGeometry):
        return frustum_mesh(geom)
    if isinstance(geom, CubeGeometry):
        return cube_mesh(geom)
    if isinstance(geom, PyramidGeometry):
        return pyramid_mesh(geom)
    if isinstance(geom, PrismGeometry):
        return prism_mesh(geom)
    raise SimulationError(f"{field}: cannot build a mesh for fixture kind {geom.kind!r}")


def yaw_matrix(yaw_rad: float) -> FloatArray:
    """Rotation about +X_D by ``yaw_rad``, (3, 3)."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def place_mesh(
    mesh: o3d.geometry.TriangleMesh, y: float, z: float, yaw_rad: float
) -> o3d.geometry.TriangleMesh:
    """A copy of ``mesh`` turned by ``yaw_rad`` about +X, then moved by (0, y, z) metres."""
    v, t = mesh_arrays(mesh)
    placed = v @ yaw_matrix(yaw_rad).T + np.array([0.0, y, z])
    return to_mesh(placed, t)
