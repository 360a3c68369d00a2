"""Recipes: one YAML file per station and fixture set, parsed into typed models.

Lengths are metres; angles carry their unit in the field name (``_deg`` or ``_rad``). Unknown keys
are errors. :func:`load_recipe` reports every problem with the YAML field path and line.
"""

from __future__ import annotations

import hashlib
import math
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import BaseModel, Field, ValidationError, model_validator

from calstation.engine.settings import (  # nested in a recipe; importable from here too
    DEFAULT_PLATTER_RADIUS as DEFAULT_PLATTER_RADIUS,
    Coordinate as Coordinate,
    CubeGeometry as CubeGeometry,
    InitialSettings as InitialSettings,
    LTargetGeometry as LTargetGeometry,
    OptimizerSettings as OptimizerSettings,
    PeriodicitySettings as PeriodicitySettings,
    PlatterGeometry as PlatterGeometry,
    QALimits as QALimits,
    Settings,
    ShapeOptions as ShapeOptions,
    ShapeSettings as ShapeSettings,
    SigmaLimits as SigmaLimits,
    Yaw as Yaw,
)
from calstation.errors import PluginError, RecipeError
from calstation.yamlsafe import YamlProblem, check_regular_file, load_yaml, read_text_file

Model = Settings
"""Base of the recipe models: the engine settings' base, so that both nest alike."""


MAX_RECIPE_BYTES = 1_000_000
"""Largest recipe file accepted (bytes)."""
MAX_MESH_BYTES = 200_000_000
"""Largest fixture mesh file accepted (bytes)."""
MAX_SCAN_POINTS = 25_000_000
"""Most lidar points one simulated scan may produce (the default spin scan takes ~3.2 million)."""
MAX_SCAN_LINES = 200_000
"""Most lidar lines one simulated scan may produce (the default spin scan takes ~3200)."""
MAX_SCAN_ENCODER_SAMPLES = 20_000_000
"""Most encoder samples one simulated scan may produce."""
MAX_SCAN_SECONDS = 600.0
"""Longest scan a recipe may ask for (settle time plus the turns), seconds."""


# --- station and drivers -------------------------------------------------------------------
class DriverConfig(Model):
    """A driver by its registered name, with the settings its factory validates."""

    driver: str = Field(min_length=1)
    settings: dict[str, Any] = Field(default_factory=dict)


class EncoderConfig(DriverConfig):
    """The encoder driver plus the station-level encoder configuration."""

    ppr: int = Field(
        1024, ge=100, le=1_000_000,
        description="pulses per revolution; counts = 4·ppr (at least 400 counts, 0.9°, per turn)",
    )
    direction: Literal[1, -1] = 1
    latency_s: float = Field(
        0.0, ge=-1.0, le=1.0, description="encoder time minus lidar time, compensated"
    )


class StationConfig(Model):
    """The station: its identity and its three drivers.

    ``id`` names the station in the database and in folder names: letters, digits, ``.``, ``_``,
    ``-``.
    """

    id: str = Field(min_length=1, max_length=100, pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
    lidar: DriverConfig
    turntable: DriverConfig
    encoder: EncoderConfig


# --- fixtures (DESIGN §3) ----------------------------------------------------------------------
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


# --- simulation (DESIGN §6) --------------------------------------------------------------------
class TruthConfig(Model):
    """The true lidar pose of the simulated station.

    Either ``range``/``pitch_deg`` plus small deviations (the paper's scenarios: the boresight
    hits the platter centre at ``range`` metres, looking down at ``pitch_deg``), or the explicit
    extrinsics ``H`` (tx, ty, tz m; rx, ry, rz rad). Deviations not given are drawn from the seed
    within the ``*_max`` bounds.
    """

    range: float = Field(1.25, ge=0.2, le=20.0)
    pitch_deg: float = Field(45.0, gt=5, lt=85)
    tx_max: float = Field(0.020, ge=0, le=0.5)
    tz_max: float = Field(0.015, ge=0, le=0.5)
    ry_max_deg: float = Field(0.5, ge=0, le=10)
    rz_max_deg: float = Field(0.5, ge=0, le=10)
    H: dict[str, Annotated[float, Field(ge=-20.0, le=20.0)]] | None = Field(
        None, description="tx, ty, tz (m, within ±20) and rx, ry, rz (rad, within ±π)"
    )


class LidarModel(Model):
    """The simulated line scanner."""

    fov_deg: float = Field(72.0, ge=1, le=360)
    points_per_line: int = Field(1000, ge=2, le=100_000)
    line_rate_hz: float = Field(1000.0, ge=1, le=100_000)
    range_noise: float = Field(0.001, ge=0, le=0.1)
    range_min: float = Field(0.2, ge=0, le=100)
    range_max: float = Field(10.0, ge=0.1, le=200)
    dropout: float = Field(0.002, ge=0, le=0.9)
    mixed_pixel_prob: float = Field(0.5, ge=0, le=1)
    beam_divergence_deg: float = Field(0.03, ge=0, le=5)
    max_points_per_second: float = Field(1.0e6, ge=1, le=1.0e8)

    @model_validator(mode="after")
    def _rate(self) -> LidarModel:
        if self.points_per_line * self.line_rate_hz > self.max_points_per_second * (1 + 1e-9):
            raise ValueError(
                f"points_per_line × line_rate_hz = {self.points_per_line * self.line_rate_hz:g} "
                f"points/s exceeds the {self.max_points_per_second:g} points/s of this lidar"
            )
        return self


class TurntableModel(Model):
    """The simulated turntable drive."""

    acceleration_rpm_s: float = Field(60.0, ge=0.1, le=10_000)
    speed_ripple: float = Field(0.005, ge=0, le=0.3, description="relative speed ripple")
    ripple_per_rev: int = Field(3, ge=0, le=100)


class EncoderModel(Model):
    """The simulated encoder's non-idealities (ppr/direction come from the station config)."""

    sample_rate_hz: float = Field(1000.0, ge=10, le=1.0e6)
    latency_s: float = Field(0.0, ge=-1.0, le=1.0)


class PlacementError(Model):
    """How far the operator misplaces fixtures (1σ)."""

    position_sigma: float = Field(0.002, ge=0, le=0.05)
    yaw_sigma_deg: float = Field(0.5, ge=0, le=10)


class BackgroundModel(Model):
    """Static scenery around the turntable, in frame P."""

    floor_depth: float = Field(
        0.8, ge=0.01, le=100, description="floor plane this far below the platter top"
    )
    wall_distance: float = Field(
        2.5, ge=0.1, le=100, description="back wall this far from the axis"
    )
    enabled: bool = True


class SimulationConfig(Model):
    """Everything the simulated station models. Seeded and deterministic."""

    seed: int = Field(0, ge=0, le=2**63 - 1)
    truth: TruthConfig = TruthConfig()
    lidar: LidarModel = LidarModel()
    turntable: TurntableModel = TurntableModel()
    encoder: EncoderModel = EncoderModel()
    placement: PlacementError = PlacementError()
    background: BackgroundModel = BackgroundModel()


# --- steps, calibration and QA -------------------------------------------------------------
class StaticScanStep(Model):
    """The static scan of the L-target."""

    lines: int = Field(100, ge=1, le=10_000)


class SpinScanStep(Model):
    """A spin scan (spin target or QA cube)."""

    rpm: float = Field(20.0, ge=0.5, le=120)
    revolutions: float = Field(1.05, ge=1.0, le=10.0, description="a little over one turn")
    settle_s: float = Field(0.5, ge=0, le=60)
    second_pass_rpm: float | None = Field(
        None, ge=-120, le=120,
        description="scan the same turns again at this signed speed (negative: the other way): "
        "the spin scan's two passes give the lidar–encoder time offset, the cube's are measured "
        "together, which shows whether that offset is right",
    )

    def second_pass(self) -> SpinScanStep | None:
        """The second pass as a scan of its own (this one at ``second_pass_rpm``), or None."""
        if self.second_pass_rpm is None:
            return None
        return self.model_copy(update={"rpm": self.second_pass_rpm, "second_pass_rpm": None})


class Steps(Model):
    """Acquisition settings per step."""

    static_scan: StaticScanStep = StaticScanStep()
    spin_scan: SpinScanStep = SpinScanStep()
    cube_scan: SpinScanStep = SpinScanStep()


class CalibrationSettings(Model):
    """Which fine-tuning strategy to run, where it starts, and each stage's settings."""

    strategy: str = "periodicity"
    start: Literal["l_target", "platter"] = Field(
        "l_target",
        description="where the fine-tuning starts: the L-target's static scan (the paper), or "
        "the platter's chord in the spin scan itself (no L-target, no static scan)",
    )
    initial: InitialSettings = InitialSettings()
    shape: ShapeSettings = ShapeSettings()
    periodicity: PeriodicitySettings = PeriodicitySettings()
    max_sigma: SigmaLimits = SigmaLimits()
    options: dict[str, dict[str, Any]] = Field(
        default_factory=dict, description="settings of plugin strategies, by strategy name"
    )


# --- the recipe ----------------------------------------------------------------------------
class Recipe(Model):
    """A whole recipe."""

    name: str = Field(min_length=1, max_length=200)
    description: str = Field("", max_length=10_000)
    version: int = Field(1, ge=1, le=1_000_000)
    station: StationConfig
    fixtures: Fixtures = Fixtures()
    simulation: SimulationConfig | None = None
    steps: Steps = Steps()
    calibration: CalibrationSettings = CalibrationSettings()
    qa: QALimits = QALimits()


class LoadedRecipe:
    """A validated recipe with where it came from: path, text and its sha256."""

    def __init__(self, recipe: Recipe, path: Path | None, text: str) -> None:
        self.recipe = recipe
        self.path = path
        self.text = text
        self.sha256 = hashlib.sha256(text.encode("utf-8")).hexdigest()

    def resolve(self, relative: str) -> Path:
        """A path named in the recipe, relative to the recipe's folder."""
        p = Path(relative)
        if p.is_absolute() or self.path is None:
            return p
        return self.path.parent / p


def _line_of(node: yaml.Node | None, loc: tuple[int | str, ...]) -> int | None:
    """1-based line of the YAML node at ``loc`` (the deepest one that exists)."""
    line = None if node is None else node.start_mark.line + 1
    for key in loc:
        if isinstance(node, yaml.MappingNode):
            for k, v in node.value:
                if k.value == key:
                    line = k.start_mark.line + 1
                    node = v
                    break
            else:
                return line
        elif isinstance(node, yaml.SequenceNode) and isinstance(key, int):
            if key >= len(node.value):
                return line
            node = node.value[key]
            line = node.start_mark.line + 1
        else:
            return line
    return line


def _format_loc(loc: tuple[int | str, ...]) -> str:
    parts: list[str] = []
    for key in loc:
        if isinstance(key, int):
            parts.append(f"[{key}]")
        else:
            parts.append(("." if parts else "") + str(key))
    return "".join(parts) or "(top level)"


def parse_recipe(text: str, source: str = "<recipe>", base_dir: Path | None = None) -> Recipe:
    """Validate recipe YAML text; :class:`RecipeError` names the field and line of each problem.

    The text is bounded first (size, nesting, duplicate keys: :mod:`calstation.yamlsafe`). After
    the field checks, :func:`cross_field_problems` runs the checks that relate fields to each
    other (and mesh files to ``base_dir``, the recipe's folder, when given).
    """
    if len(text) > MAX_RECIPE_BYTES:
        raise RecipeError(
            f"{source}: the recipe is {len(text) / 1e6:.1f} MB, more than the "
            f"{MAX_RECIPE_BYTES / 1e6:g} MB calstation accepts"
        )
    try:
        data, node = load_yaml(text)
    except YamlProblem as exc:
        where = f"{source}:{exc.line}" if exc.line else source
        field = f"{_format_loc(exc.loc)}: " if exc.loc else ""
        raise RecipeError(f"invalid recipe:\n  {where}: {field}{exc.message}") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{source}:{mark.line + 1}" if mark is not None else source
        problem = getattr(exc, "problem", None) or str(exc)
        raise RecipeError(f"{where}: not valid YAML: {problem}") from None
    except RecursionError:  # not reached after the depth check; kept as a last guard
        raise RecipeError(f"{source}: the recipe is nested too deeply") from None
    if not isinstance(data, dict):
        raise RecipeError(f"{source}: a recipe must be a YAML mapping, got {type(data).__name__}")
    try:
        recipe = Recipe.model_validate(data)
    except ValidationError as exc:
        problems = []
        for err in exc.errors():
            loc = tuple(k for k in err["loc"] if not _is_union_tag(k))
            line = _line_of(node, loc)
            where = f"{source}:{line}" if line else source
            problems.append(f"{where}: {_format_loc(loc)}: {_message(err)}")
        raise RecipeError("invalid recipe:\n  " + "\n  ".join(problems)) from None
    cross = cross_field_problems(recipe, base_dir)
    if cross:
        raise RecipeError(_format_problems(cross, node, source))
    return recipe


def _message(err: Any) -> str:
    """A pydantic error in the recipe's words (the value it got included where it helps)."""
    if err["type"] == "extra_forbidden":
        return "unknown key"
    msg = str(err["msg"])
    if err["type"] in ("finite_number", "float_parsing", "int_parsing", "int_from_float"):
        return f"{msg} (got {err.get('input')!r})"
    if err["type"] in ("greater_than", "greater_than_equal", "less_than", "less_than_equal"):
        return f"{msg} (got {err.get('input')!r})"
    return msg


Problem = tuple[tuple[int | str, ...], str]
"""A validation problem: the field path in the recipe and what is wrong."""


def _format_problems(problems: list[Problem], node: yaml.Node | None, source: str) -> str:
    lines = []
    for loc, msg in problems:
        line = _line_of(node, loc)
        where = f"{source}:{line}" if line else source
        lines.append(f"{where}: {_format_loc(loc)}: {msg}")
    return "invalid recipe:\n  " + "\n  ".join(lines)


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


def _footprint_radius(geometry: Any) -> float:
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


def _fixture_problems(
    loc: tuple[int | str, ...], geometry: Any, radius: float, base_dir: Path | None
) -> list[Problem]:
    """A fixture's mesh loads, its shape can be built, and its footprint is on the platter."""
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


def _size_field(geometry: Any) -> str:
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


SECOND_PASS_CONTRAST = 0.5
"""A second pass's speed must differ from the first's by at least this fraction of it: the time
offset is seen through the difference of the two speeds."""


def _scans(steps: Steps) -> list[tuple[str, SpinScanStep]]:
    """Each spin scan a run takes, by its step name (a second pass as one more scan)."""
    out = []
    for name in ("spin_scan", "cube_scan"):
        cfg: SpinScanStep = getattr(steps, name)
        out.append((name, cfg))
        second = cfg.second_pass()
        if second is not None and abs(second.rpm) >= 0.5:  # else refused by its own check
            out.append((name, second))
    return out


def _second_pass_problems(steps: Steps, turntable: str) -> list[Problem]:
    """A second pass turns at a usable speed that differs enough from the first pass's (and is
    not asked of the replay drivers, which play one recording per fixture)."""
    problems: list[Problem] = []
    for name in ("spin_scan", "cube_scan"):
        cfg: SpinScanStep = getattr(steps, name)
        first, second = cfg.rpm, cfg.second_pass_rpm
        if second is None:
            continue
        where = ("steps", name, "second_pass_rpm")
        if turntable == "replay":
            problems.append((where, "the replay drivers play one recording per fixture and "
                                    "cannot replay a second pass: re-process the run with "
                                    "`calstation calibrate --run N`, or remove it"))
        elif abs(second) < 0.5:
            problems.append((where, f"{second:g} rpm: a second pass turns at 0.5 … 120 rpm, "
                                    "either way (negative turns the other way)"))
        elif abs(second - first) < SECOND_PASS_CONTRAST * abs(first):
            problems.append((where, f"{second:g} rpm is too close to the first pass's {first:g} "
                                    "rpm to show the time offset: turn the other way "
                                    f"({-first:g}) or differ by at least "
                                    f"{SECOND_PASS_CONTRAST * abs(first):g} rpm"))
    return problems


def _scan_problems(recipe: Recipe) -> list[Problem]:
    """Scans must end: bounded in time, and (simulated) in the number of points."""
    problems: list[Problem] = []
    # the simulated scanner makes every point the model asks for; a real (or emulated) lidar
    # streams at its own rate, checked by the time bound only
    sim = recipe.simulation if recipe.station.lidar.driver == "sim" else None
    rate = 0.0 if sim is None else sim.lidar.points_per_line * sim.lidar.line_rate_hz
    line_rate = 0.0 if sim is None else sim.lidar.line_rate_hz
    sample_rate = 0.0 if sim is None else sim.encoder.sample_rate_hz
    accel = 60.0 if sim is None else sim.turntable.acceleration_rpm_s
    problems += _second_pass_problems(recipe.steps, recipe.station.turntable.driver)
    for name, cfg in _scans(recipe.steps):
        seconds = cfg.settle_s + abs(cfg.rpm) / accel + cfg.revolutions * 60.0 / abs(cfg.rpm)
        if seconds > MAX_SCAN_SECONDS:
            problems.append((("steps", name, "revolutions"),
                             f"{cfg.revolutions:g} turns at {cfg.rpm:g} rpm take {seconds:.0f} s, "
                             f"more than the {MAX_SCAN_SECONDS:g} s a scan may last"))
        elif rate and seconds * rate > MAX_SCAN_POINTS:
            problems.append((("steps", name, "revolutions"),
                             f"{cfg.revolutions:g} turns at {cfg.rpm:g} rpm make about "
                             f"{seconds * rate / 1e6:.0f} million simulated points, more than "
                             f"the {MAX_SCAN_POINTS / 1e6:g} million a scan may hold: raise rpm "
                             "or lower the lidar's points_per_line × line_rate_hz"))
        elif line_rate and seconds * line_rate > MAX_SCAN_LINES:
            problems.append((("steps", name, "revolutions"),
                             f"{cfg.revolutions:g} turns at {cfg.rpm:g} rpm make about "
                             f"{seconds * line_rate:,.0f} simulated lidar lines, more than the "
                             f"{MAX_SCAN_LINES:,} a scan may hold"))
        elif sample_rate and seconds * sample_rate > MAX_SCAN_ENCODER_SAMPLES:
            problems.append((("steps", name, "revolutions"),
                             f"{cfg.revolutions:g} turns at {cfg.rpm:g} rpm make about "
                             f"{seconds * sample_rate / 1e6:.0f} million simulated encoder "
                             f"samples, more than the {MAX_SCAN_ENCODER_SAMPLES / 1e6:g} million "
                             "a scan may hold"))
    if sim is not None:
        lines = recipe.steps.static_scan.lines
        if lines * sim.lidar.points_per_line > MAX_SCAN_POINTS:
            problems.append((("steps", "static_scan", "lines"),
                             f"{lines} lines of {sim.lidar.points_per_line} points are more than "
                             f"the {MAX_SCAN_POINTS / 1e6:g} million points a scan may hold"))
    return problems


def _simulation_problems(recipe: Recipe) -> list[Problem]:
    sim = recipe.simulation
    if sim is None:
        return []
    problems: list[Problem] = []
    fixtures = recipe.fixtures
    spin = fixtures.spin_target
    if isinstance(spin, FrustumGeometry) and spin.slope_deg >= sim.truth.pitch_deg:
        problems.append(
            (
                ("fixtures", "spin_target", "slope_deg"),
                f"facets sloped {spin.slope_deg:g}° are not seen in both half-turns by a "
                f"lidar pitched {sim.truth.pitch_deg:g}° (simulation.truth.pitch_deg); "
                "the slope must be smaller than the pitch",
            )
        )
    lidar = sim.lidar
    if lidar.range_min >= lidar.range_max:
        problems.append((("simulation", "lidar", "range_min"), "must be smaller than range_max"))
    elif sim.truth.H is None and not lidar.range_min < sim.truth.range < lidar.range_max:
        problems.append((("simulation", "truth", "range"),
                         f"the platter at {sim.truth.range:g} m is outside the lidar's range "
                         f"window [{lidar.range_min:g}, {lidar.range_max:g}] m"))
    if sim.truth.H is not None:
        missing = [k for k in PARAM_NAMES if k not in sim.truth.H and k != "rx"]
        if missing:
            problems.append((("simulation", "truth", "H"),
                             f"missing {', '.join(missing)} (tx, ty, tz, ry, rz are needed; rx "
                             "defaults to 0)"))
        for key, value in sim.truth.H.items():
            if key not in PARAM_NAMES:
                problems.append((("simulation", "truth", "H", key),
                                 f"unknown parameter {key!r}; expected tx, ty, tz, rx, ry, rz"))
            elif key.startswith("r") and abs(value) > math.pi:
                problems.append((("simulation", "truth", "H", key),
                                 f"{value:g} rad is not an angle in [-π, π]"))
    accel = sim.turntable.acceleration_rpm_s
    preflight_rpm = recipe.steps.spin_scan.rpm
    if accel * PREFLIGHT_RAMP_S < 0.5 * preflight_rpm:
        problems.append((("simulation", "turntable", "acceleration_rpm_s"),
                         f"{accel:g} rpm/s does not bring the platter to half of "
                         f"steps.spin_scan.rpm ({preflight_rpm:g}) within the preflight's "
                         f"{PREFLIGHT_RAMP_S:g} s spin-up: at least {preflight_rpm / 3:g} rpm/s"))
    background = sim.background
    if background.enabled and background.wall_distance <= fixtures.platter.radius + 0.05:
        problems.append((("simulation", "background", "wall_distance"),
                         f"the wall {background.wall_distance:g} m from the axis cuts the platter "
                         f"(radius {fixtures.platter.radius:g} m)"))
    if background.enabled and background.floor_depth <= fixtures.platter.thickness:
        problems.append((("simulation", "background", "floor_depth"),
                         "the floor must lie below the platter's thickness"))
    return problems


PARAM_NAMES = ("tx", "ty", "tz", "rx", "ry", "rz")
PREFLIGHT_RAMP_S = 1.5
"""How long the station's preflight lets the platter spin up before it counts (station.py)."""


class PeriodicityOptions(Model):
    """``calibration.options.periodicity``: the built-in periodicity strategy takes its settings
    from ``calibration.periodicity``; no options."""


BUILTIN_OPTIONS: dict[str, type[BaseModel]] = {
    "shape": ShapeOptions,
    "periodicity": PeriodicityOptions,
}
"""The options models of the built-in strategies (plugins declare theirs as the strategy's
``options_model``; see :func:`options_problems`)."""


def options_problems(name: str, model: type[BaseModel], options: Any) -> list[Problem]:
    """Problems of ``calibration.options.<name>`` against the strategy's options ``model``."""
    try:
        model.model_validate(options if options is not None else {})
    except ValidationError as exc:
        return [(("calibration", "options", name, *err["loc"]), _message(err))
                for err in exc.errors()]
    return []


def cross_field_problems(recipe: Recipe, base_dir: Path | None = None) -> list[Problem]:
    """Checks that relate fields to each other; each problem names the field it is about.

    Fixtures must be buildable (simple polygons, meshes that load) and stand on the platter,
    footprint included; the spin target's facets must be flatter than the lidar's pitch (else
    they are seen in one half-turn only); scans must end in bounded time and points; the
    simulated lidar's range window must hold the platter; explicit true extrinsics name only
    tx..rz; built-in strategies' options are checked.
    """
    problems: list[Problem] = []
    fixtures = recipe.fixtures
    radius = fixtures.platter.radius
    named: list[tuple[tuple[int | str, ...], Any]] = [
        (("fixtures", "static_target"), fixtures.static_target),
        (("fixtures", "spin_target"), fixtures.spin_target),
        (("fixtures", "qa_cube"), fixtures.qa_cube),
    ] + [(("fixtures", "demo", i), g) for i, g in enumerate(fixtures.demo)]
    for loc, geometry in named:
        problems += _fixture_problems(loc, geometry, radius, base_dir)
    lt = fixtures.static_target
    if lt.base_length <= lt.wall_thickness:
        problems.append(
            (("fixtures", "static_target", "base_length"), "must be longer than wall_thickness")
        )
    problems += _simulation_problems(recipe)
    problems += _scan_problems(recipe)
    for name, model in BUILTIN_OPTIONS.items():
        if name in recipe.calibration.options:
            problems += options_problems(name, model, recipe.calibration.options[name])
    return problems


def settings_model_of(factory: object) -> Any:
    """The pydantic model a driver factory declares for its ``settings`` (None if none): its
    ``settings_model``, given as the class or, so that registering costs no import, as the
    class's import path ``"package.module:Class"`` (imported here, when a recipe is checked)."""
    model = getattr(factory, "settings_model", None)
    if isinstance(model, str):
        import importlib

        module, _, name = model.partition(":")
        try:
            model = getattr(importlib.import_module(module), name)
        except (ImportError, AttributeError) as exc:
            raise PluginError(
                f"the driver factory {factory!r} declares settings_model {model!r}, which cannot "
                f"be imported: {exc}"
            ) from exc
    return model


def plugin_problems(recipe: Recipe) -> list[Problem]:
    """Checks against the installed plugins: drivers and strategies named must be registered,
    each driver's ``settings`` must fit the ``settings_model`` its factory declares, and each
    strategy's options the ``options_model`` it declares."""
    from calstation import plugins

    problems: list[Problem] = []
    registered = plugins.drivers()
    for kind in plugins.DRIVER_KINDS:
        config = getattr(recipe.station, kind)
        name = config.driver
        settings_model = settings_model_of(registered[(kind, name)].factory) if (
            kind, name) in registered else None
        if settings_model is not None:
            try:
                settings_model.model_validate(config.settings)
            except ValidationError as exc:
                problems += [(("station", kind, "settings", *err["loc"]), _message(err))
                             for err in exc.errors()]
        if (kind, name) not in registered:
            known = sorted(n for (k, n) in registered if k == kind)
            problems.append(
                (
                    ("station", kind, "driver"),
                    f"no {kind} driver named {name!r} is installed; "
                    f"installed: {', '.join(known) or 'none'}",
                )
            )
    strategies = plugins.strategies()
    if recipe.calibration.strategy not in strategies:
        problems.append(
            (
                ("calibration", "strategy"),
                f"no fine-tuning strategy named {recipe.calibration.strategy!r} is installed; "
                f"installed: {', '.join(sorted(strategies)) or 'none'}",
            )
        )
    for name in recipe.calibration.options:
        if name not in strategies:
            problems.append(
                (("calibration", "options", name), f"options for unknown strategy {name!r}")
            )
    from calstation.plugins.cost_strategies import recipe_option_problems

    problems += recipe_option_problems(recipe, strategies)
    return problems


def check_plugins(loaded: LoadedRecipe) -> None:
    """Raise :class:`RecipeError` (field and line of each problem) if a driver or strategy the
    recipe names is not installed, or a strategy's options do not fit its options model."""
    problems = plugin_problems(loaded.recipe)
    if problems:
        source = str(loaded.path) if loaded.path is not None else "<recipe>"
        _, node = load_yaml(loaded.text)
        raise RecipeError(_format_problems(problems, node, source))


_UNION_TAGS = {
    "l_target",
    "frustum",
    "cube",
    "pyramid",
    "prism",
    "mesh",
}


def _is_union_tag(key: int | str) -> bool:
    return isinstance(key, str) and key in _UNION_TAGS


def load_recipe(path: str | Path) -> LoadedRecipe:
    """Read and validate a recipe file.

    Only a regular file of at most :data:`MAX_RECIPE_BYTES` is read (a FIFO or a device is
    refused, never opened). Raises :class:`RecipeError` if the file is missing, is not YAML, or
    fails validation; the message names the file, each field and its line.
    """
    p = Path(path)
    try:
        text = read_text_file(p, "recipe", MAX_RECIPE_BYTES)
    except ValueError as exc:
        message = str(exc)
        if message == "recipe not found":
            message = "recipe file not found"
        raise RecipeError(f"{p}: {message}") from None
    return LoadedRecipe(parse_recipe(text, str(p), p.parent), p, text)
