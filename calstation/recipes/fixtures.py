"""The fixtures section of a recipe (DESIGN §3), and the checks that a fixture can be built and
stands on the platter.

The L-target, cube and platter geometries are the engine's (:mod:`calstation.engine.settings`);
the spin target's frustum, the demo objects and mesh fixtures are defined here. Lengths are
metres in frame D; a fixture's ``offset`` is (y, z) of its origin from the platter axis.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field

from calstation.engine.settings import (
    Coordinate,
    CubeGeometry,
    LTargetGeometry,
    PlatterGeometry,
    Yaw,
)
from calstation.recipes.base import Model
from calstation.recipes.problems import Problem
from calstation.yamlsafe import check_regular_file

MAX_MESH_BYTES = 200_000_000
"""Largest fixture mesh file accepted (bytes)."""


class FrustumGeometry(Model):
    """The spin target of periodicity fine-tuning: a polygonal frustum with sloped facets.

    ``polygon`` is the base outline, (y, z) pairs in metres in frame D, counter-clockwise; the
    top face is the base scaled by ``top_scale`` about the polygon centroid and lifted by
    ``height``. The default is the concave heptagon of DESIGN §3.
    """

    kind: Literal["frustum"] = "frustum"
    polygon: list[tuple[Coordinate, Coordinate]] | None = Field(
        None, min_length=3, max_length=64
    )
    circumradius: float = Field(0.20, ge=0.01, le=1.5)
    notch_depth: float = Field(
        0.45, ge=0, le=0.9, description="fraction of the circumradius the notch vertex moves in"
    )
    slope_deg: float = Field(20.0, gt=1, lt=89)
    height: float = Field(0.055, ge=0.001, le=0.5)
    offset: tuple[Coordinate, Coordinate] = (0.0, 0.0)
    yaw_deg: Yaw = 0.0
    mesh: str | None = None


class PyramidGeometry(Model):
    """A square pyramid (demo object)."""

    kind: Literal["pyramid"] = "pyramid"
    base: float = Field(0.150, ge=0.01, le=1.0)
    height: float = Field(0.150, ge=0.001, le=1.0)
    offset: tuple[Coordinate, Coordinate] = (0.0, 0.0)
    yaw_deg: Yaw = 0.0
    mesh: str | None = None


class PrismGeometry(Model):
    """A triangular prism lying on a rectangular face (demo object)."""

    kind: Literal["prism"] = "prism"
    edge: float = Field(0.150, ge=0.01, le=1.0)
    depth: float = Field(0.225, ge=0.01, le=1.5)
    offset: tuple[Coordinate, Coordinate] = (0.0, 0.0)
    yaw_deg: Yaw = 0.0
    mesh: str | None = None


class MeshGeometry(Model):
    """Any fixture given only as a mesh file (metres, frame D: +X up from the platter top)."""

    kind: Literal["mesh"] = "mesh"
    mesh: str = Field(min_length=1)
    offset: tuple[Coordinate, Coordinate] = (0.0, 0.0)
    yaw_deg: Yaw = 0.0


FixtureGeometry = Annotated[
    LTargetGeometry
    | FrustumGeometry
    | CubeGeometry
    | PyramidGeometry
    | PrismGeometry
    | MeshGeometry,
    Field(discriminator="kind"),
]


class Fixtures(Model):
    """Every fixture a run places on the platter."""

    platter: PlatterGeometry = PlatterGeometry()
    static_target: LTargetGeometry = LTargetGeometry()
    spin_target: FixtureGeometry = FrustumGeometry()
    qa_cube: CubeGeometry = CubeGeometry()
    demo: list[FixtureGeometry] = Field(default_factory=list)


# --- geometry that must be buildable ---------------------------------------------------------
def frustum_outline(geometry: FrustumGeometry) -> list[tuple[float, float]]:
    """The spin target's base outline (y, z) in metres: the recipe's polygon, or the default
    heptagon of ``circumradius`` with vertex 0 pulled in by ``notch_depth`` (as the simulator
    builds it)."""
    if geometry.polygon is not None:
        return [(float(y), float(z)) for y, z in geometry.polygon]
    out = []
    for i in range(7):
        a = 2.0 * math.pi * i / 7
        r = geometry.circumradius * ((1.0 - geometry.notch_depth) if i == 0 else 1.0)
        out.append((r * math.cos(a), r * math.sin(a)))
    return out


def _cross(o: tuple[float, float], a: tuple[float, float], b: tuple[float, float]) -> float:
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])


def _segments_meet(
    p1: tuple[float, float], p2: tuple[float, float], q1: tuple[float, float],
    q2: tuple[float, float], eps: float,
) -> bool:
    """Whether segments p1p2 and q1q2 intersect or touch (within ``eps`` m)."""
    d1, d2 = _cross(q1, q2, p1), _cross(q1, q2, p2)
    d3, d4 = _cross(p1, p2, q1), _cross(p1, p2, q2)
    if ((d1 > 0) != (d2 > 0)) and ((d3 > 0) != (d4 > 0)) and min(
        abs(d1), abs(d2), abs(d3), abs(d4)
    ) > 0:
        return True

    def near(a: tuple[float, float], b: tuple[float, float], c: tuple[float, float]) -> bool:
        # distance from c to segment ab
        ab = (b[0] - a[0], b[1] - a[1])
        n2 = ab[0] ** 2 + ab[1] ** 2
        t = 0.0 if n2 == 0 else max(0.0, min(1.0, ((c[0] - a[0]) * ab[0]
                                                    + (c[1] - a[1]) * ab[1]) / n2))
        return math.hypot(a[0] + t * ab[0] - c[0], a[1] + t * ab[1] - c[1]) < eps

    return near(p1, p2, q1) or near(p1, p2, q2) or near(q1, q2, p1) or near(q1, q2, p2)


POLYGON_MIN_SPACING = 0.001
"""Closest two polygon vertices (or a vertex and a non-adjacent edge) may be, metres."""
POLYGON_MIN_TURN_DEG = 1.0
"""Smallest turn at a polygon vertex, degrees: less is a collinear (useless) vertex."""


def polygon_problems(poly: list[tuple[float, float]]) -> list[tuple[int | None, str]]:
    """Why ``poly`` (y, z vertices, m) is not a simple, non-degenerate polygon; each problem
    with the index of the vertex it is about (None for the whole polygon). Empty when fine."""
    n = len(poly)
    for i in range(n):
        for j in range(i + 1, n):
            if math.dist(poly[i], poly[j]) < POLYGON_MIN_SPACING:
                return [(j, f"vertices {i} and {j} coincide (closer than "
                            f"{POLYGON_MIN_SPACING * 1000:g} mm)")]
    sin_min = math.sin(math.radians(POLYGON_MIN_TURN_DEG))
    for i in range(n):
        a, b, c = poly[i - 1], poly[i], poly[(i + 1) % n]
        if abs(_cross(a, b, c)) <= sin_min * math.dist(a, b) * math.dist(b, c):
            return [(i, f"vertex {i} is collinear with its neighbours {(i - 1) % n} and "
                        f"{(i + 1) % n} (a polygon turns at every vertex)")]
    for i in range(n):
        for j in range(i + 1, n):
            if j == i + 1 or (i == 0 and j == n - 1):
                continue  # adjacent edges share a vertex
            if _segments_meet(poly[i], poly[(i + 1) % n], poly[j], poly[(j + 1) % n],
                              POLYGON_MIN_SPACING):
                return [(None, f"the polygon crosses itself: edge {i}–{(i + 1) % n} meets "
                               f"edge {j}–{(j + 1) % n}")]
    return []


def _polygon_area_centroid(
    poly: list[tuple[float, float]],
) -> tuple[float, tuple[float, float]]:
    area = cy = cz = 0.0
    for (y0, z0), (y1, z1) in zip(poly, poly[1:] + poly[:1], strict=True):
        c = y0 * z1 - y1 * z0
        area += c
        cy += (y0 + y1) * c
        cz += (z0 + z1) * c
    area *= 0.5
    return area, (cy / (6.0 * area), cz / (6.0 * area))


def frustum_problems(geometry: FrustumGeometry) -> list[Problem]:
    """Whether the simulator (and a workshop) can build this frustum: a simple polygon, star-shaped
    from its centroid (the caps are fan-triangulated) and wide enough for the requested height at
    the requested slope. Locations are relative to the spin target."""
    poly = frustum_outline(geometry)
    field: tuple[int | str, ...] = ("polygon",) if geometry.polygon is not None else (
        "notch_depth",)
    found = polygon_problems(poly)
    if found:
        index, msg = found[0]
        loc = field + ((index,) if index is not None and geometry.polygon is not None else ())
        return [(loc, msg)]
    area, centroid = _polygon_area_centroid(poly)
    if area < 0:
        poly = poly[::-1]
    rel = [(y - centroid[0], z - centroid[1]) for y, z in poly]
    for i in range(len(rel)):
        if _cross((0.0, 0.0), rel[i], rel[(i + 1) % len(rel)]) <= 0:
            return [(field, "the polygon is not star-shaped from its centroid: the edge "
                            f"after vertex {i} turns away from it (every vertex must be visible "
                            "from the centroid)")]
    distances = []
    for (y0, z0), (y1, z1) in zip(poly, poly[1:] + poly[:1], strict=True):
        ey, ez = y1 - y0, z1 - z0
        distances.append(abs((y0 - centroid[0]) * ez - (z0 - centroid[1]) * ey)
                         / math.hypot(ey, ez))
    distances.sort()
    m = len(distances)
    median = distances[m // 2] if m % 2 else 0.5 * (distances[m // 2 - 1] + distances[m // 2])
    inset = geometry.height / math.tan(math.radians(geometry.slope_deg))
    if 1.0 - inset / median <= 0.02:
        return [(("height",), f"a frustum {geometry.height:g} m high with facets sloped "
                              f"{geometry.slope_deg:g}° needs an inset of {inset:.3f} m, more "
                              f"than its outline allows ({median:.3f} m median edge distance "
                              "from the centroid): lower the height or raise slope_deg")]
    return []


def mesh_footprint(path: Path) -> float:
    """Largest distance (m) of a mesh file's vertices from its X axis (the fixture's footprint
    radius). ValueError says why the file cannot be used: not a regular STL/PLY/OBJ file under
    :data:`MAX_MESH_BYTES`, no triangles, non-finite vertices."""
    if path.suffix.lower() not in {".stl", ".ply", ".obj"}:
        raise ValueError(f"{path} is not an STL, PLY or OBJ mesh")
    check_regular_file(path, "mesh file", MAX_MESH_BYTES)
    import numpy as np

    from calstation.quiet import quiet_open3d

    with quiet_open3d() as o3d:
        mesh = o3d.io.read_triangle_mesh(str(path))
    vertices = np.asarray(mesh.vertices)
    if len(mesh.triangles) == 0 or len(vertices) == 0:
        raise ValueError(f"mesh file {path} holds no triangles (unreadable or empty)")
    if not np.isfinite(vertices).all():
        raise ValueError(f"mesh file {path} has non-finite vertices")
    return float(np.hypot(vertices[:, 1], vertices[:, 2]).max())


def _footprint_radius(geometry: object) -> float:
    """Radius (m) of the circle around the fixture's own origin that holds its base outline."""
    if isinstance(geometry, LTargetGeometry):
        return math.hypot(max(geometry.base_length, geometry.wall_thickness),
                          0.5 * geometry.width)
    if isinstance(geometry, CubeGeometry):
        return geometry.edge / math.sqrt(2.0)
    if isinstance(geometry, PyramidGeometry):
        return geometry.base / math.sqrt(2.0)
    if isinstance(geometry, PrismGeometry):
        return 0.5 * math.hypot(geometry.edge, geometry.depth)
    if isinstance(geometry, FrustumGeometry):
        return max(math.hypot(y, z) for y, z in frustum_outline(geometry))
    return 0.0


def fixture_problems(
    loc: tuple[int | str, ...], geometry: object, radius: float, base_dir: Path | None
) -> list[Problem]:
    """The problems of one fixture, located under ``loc``: its mesh loads (a relative path from
    ``base_dir``, the recipe's folder; not looked for without one), its shape can be built, and
    its footprint stands on the platter of ``radius`` metres."""
    problems: list[Problem] = []
    footprint: float | None = None
    if isinstance(geometry, FrustumGeometry) and not geometry.mesh:
        found = frustum_problems(geometry)
        problems += [((*loc, *sub), msg) for sub, msg in found]
        if found:
            return problems
    mesh = getattr(geometry, "mesh", None)
    if mesh:
        path = Path(mesh)
        if not path.is_absolute() and base_dir is not None:
            path = base_dir / path
        if base_dir is not None or path.is_absolute():
            try:
                footprint = mesh_footprint(path)
            except ValueError as exc:
                msg = str(exc)
                if msg == "mesh file not found":
                    msg = f"mesh file not found: {path}"
                return [*problems, ((*loc, "mesh"), msg)]
    if footprint is None:
        footprint = _footprint_radius(geometry)
    offset = getattr(geometry, "offset", (0.0, 0.0))
    reach = math.hypot(*offset) + footprint
    if reach > radius + 1e-9:
        # the size is at fault when the fixture would not fit even centred; else the offset
        what = "offset" if footprint <= radius + 1e-9 else _size_field(geometry)
        problems.append(
            (
                (*loc, what),
                f"the fixture reaches {reach * 1000:.0f} mm from the axis, off the platter "
                f"(radius {radius * 1000:.0f} mm)",
            )
        )
    return problems


def _size_field(geometry: object) -> str:
    """The field that sets a fixture's size (named when a centred fixture is too big)."""
    if getattr(geometry, "mesh", None):
        return "mesh"
    if isinstance(geometry, LTargetGeometry):
        return "width" if geometry.width / 2 >= geometry.base_length else "base_length"
    if isinstance(geometry, FrustumGeometry):
        return "polygon" if geometry.polygon is not None else "circumradius"
    if isinstance(geometry, PyramidGeometry):
        return "base"
    return "edge"

