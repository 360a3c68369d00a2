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
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from .errors import RecipeError

Positive = Annotated[float, Field(gt=0)]
NonNegative = Annotated[float, Field(ge=0)]


class Model(BaseModel):
    """Base for recipe models: unknown keys are errors, values are immutable."""

    model_config = ConfigDict(extra="forbid", frozen=True)


# --- station and drivers -------------------------------------------------------------------
class DriverConfig(Model):
    """A driver by its registered name, with the settings its factory validates."""

    driver: str = Field(min_length=1)
    settings: dict[str, Any] = Field(default_factory=dict)


class EncoderConfig(DriverConfig):
    """The encoder driver plus the station-level encoder configuration."""

    ppr: int = Field(1024, gt=0, description="pulses per revolution; counts = 4·ppr")
    direction: Literal[1, -1] = 1
    latency_s: float = Field(0.0, description="encoder time minus lidar time, compensated")


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
class PlatterGeometry(Model):
    """The turntable's platter: a disk whose top surface is the P frame's origin plane."""

    diameter: Positive = 0.585
    thickness: Positive = 0.010

    @property
    def radius(self) -> float:
        """Half the diameter, metres."""
        return 0.5 * self.diameter


DEFAULT_PLATTER_RADIUS = PlatterGeometry().radius
"""The default platter's radius (m), for library functions called without a recipe; the
station, the CLI and the bench always pass the recipe's ``platter.radius``."""


class LTargetGeometry(Model):
    """The static L-shaped target of the initial calibration (paper §III-A).

    Base plate along Y_P from A (front, toward the lidar) to the back wall at B; the wall rises
    along X_P; ``width`` runs along Z_P; wall height above the base top is ``h_tall`` at
    z_P = −width/2 and ``h_short`` at +width/2 (linear, ``h_mid`` at the centre).
    """

    kind: Literal["l_target"] = "l_target"
    base_length: Positive = 0.15
    base_thickness: Positive = 0.010
    wall_thickness: Positive = 0.010
    width: Positive = 0.20
    h_tall: Positive = 0.15
    h_mid: Positive = 0.10
    h_short: Positive = 0.05
    offset: tuple[float, float] = Field(
        (0.0, 0.0), description="(y_P, z_P) of B relative to the platter centre, metres"
    )
    mesh: str | None = Field(None, description="optional CAD mesh (STL/PLY/OBJ) in frame D")

    @model_validator(mode="after")
    def _heights(self) -> LTargetGeometry:
        if not self.h_tall > self.h_short:
            raise ValueError("h_tall must be greater than h_short")
        if not self.h_short < self.h_mid < self.h_tall:
            raise ValueError("h_mid must lie between h_short and h_tall")
        if not math.isclose(self.h_mid, 0.5 * (self.h_tall + self.h_short), rel_tol=0.02):
            raise ValueError("h_mid must be the mean of h_tall and h_short (linear wall top)")
        return self


class FrustumGeometry(Model):
    """The spin target of periodicity fine-tuning: a polygonal frustum with sloped facets.

    ``polygon`` is the base outline, (y, z) pairs in metres in frame D, counter-clockwise; the
    top face is the base scaled by ``top_scale`` about the polygon centroid and lifted by
    ``height``. The default is the concave heptagon of DESIGN §3.
    """

    kind: Literal["frustum"] = "frustum"
    polygon: list[tuple[float, float]] | None = None
    circumradius: Positive = 0.20
    notch_depth: NonNegative = Field(
        0.45, le=0.9, description="fraction of the circumradius the notch vertex moves in"
    )
    slope_deg: float = Field(20.0, gt=1, lt=89)
    height: Positive = 0.055
    offset: tuple[float, float] = (0.0, 0.0)
    yaw_deg: float = 0.0
    mesh: str | None = None

    @model_validator(mode="after")
    def _polygon(self) -> FrustumGeometry:
        if self.polygon is not None and len(self.polygon) < 3:
            raise ValueError("polygon needs at least 3 vertices")
        return self


class CubeGeometry(Model):
    """A cube of edge ``edge`` standing on the platter (the QA cube)."""

    kind: Literal["cube"] = "cube"
    edge: Positive = 0.100
    offset: tuple[float, float] = (0.08, 0.05)
    yaw_deg: float = 20.0
    mesh: str | None = None


class PyramidGeometry(Model):
    """A square pyramid (demo object)."""

    kind: Literal["pyramid"] = "pyramid"
    base: Positive = 0.150
    height: Positive = 0.150
    offset: tuple[float, float] = (0.0, 0.0)
    yaw_deg: float = 0.0
    mesh: str | None = None


class PrismGeometry(Model):
    """A triangular prism lying on a rectangular face (demo object)."""

    kind: Literal["prism"] = "prism"
    edge: Positive = 0.150
    depth: Positive = 0.225
    offset: tuple[float, float] = (0.0, 0.0)
    yaw_deg: float = 0.0
    mesh: str | None = None


class MeshGeometry(Model):
    """Any fixture given only as a mesh file (metres, frame D: +X up from the platter top)."""

    kind: Literal["mesh"] = "mesh"
    mesh: str
    offset: tuple[float, float] = (0.0, 0.0)
    yaw_deg: float = 0.0


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

    range: Positive = 1.25
    pitch_deg: float = Field(45.0, gt=5, lt=85)
    tx_max: NonNegative = 0.020
    tz_max: NonNegative = 0.015
    ry_max_deg: NonNegative = 0.5
    rz_max_deg: NonNegative = 0.5
    H: dict[str, float] | None = None


class LidarModel(Model):
    """The simulated line scanner."""

    fov_deg: float = Field(72.0, gt=0, le=360)
    points_per_line: int = Field(1000, gt=1)
    line_rate_hz: Positive = 1000.0
    range_noise: NonNegative = 0.001
    range_min: NonNegative = 0.2
    range_max: Positive = 10.0
    dropout: float = Field(0.002, ge=0, lt=1)
    mixed_pixel_prob: float = Field(0.5, ge=0, le=1)
    beam_divergence_deg: NonNegative = 0.03
    max_points_per_second: Positive = 1.0e6

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

    acceleration_rpm_s: Positive = 60.0
    speed_ripple: float = Field(0.005, ge=0, lt=0.5, description="relative speed ripple")
    ripple_per_rev: int = Field(3, ge=0)


class EncoderModel(Model):
    """The simulated encoder's non-idealities (ppr/direction come from the station config)."""

    sample_rate_hz: Positive = 1000.0
    latency_s: float = 0.0


class PlacementError(Model):
    """How far the operator misplaces fixtures (1σ)."""

    position_sigma: NonNegative = 0.002
    yaw_sigma_deg: NonNegative = 0.5


class BackgroundModel(Model):
    """Static scenery around the turntable, in frame P."""

    floor_depth: Positive = Field(0.8, description="floor plane this far below the platter top")
    wall_distance: Positive = Field(2.5, description="back wall this far from the axis")
    enabled: bool = True


class SimulationConfig(Model):
    """Everything the simulated station models. Seeded and deterministic."""

    seed: int = 0
    truth: TruthConfig = TruthConfig()
    lidar: LidarModel = LidarModel()
    turntable: TurntableModel = TurntableModel()
    encoder: EncoderModel = EncoderModel()
    placement: PlacementError = PlacementError()
    background: BackgroundModel = BackgroundModel()


# --- steps, calibration and QA -------------------------------------------------------------
class StaticScanStep(Model):
    """The static scan of the L-target."""

    lines: int = Field(100, gt=0)


class SpinScanStep(Model):
    """A spin scan (spin target or QA cube)."""

    rpm: float = Field(20.0, gt=0)
    revolutions: float = Field(1.05, ge=1.0, description="a little over one turn")
    settle_s: NonNegative = 0.5


class Steps(Model):
    """Acquisition settings per step."""

    static_scan: StaticScanStep = StaticScanStep()
    spin_scan: SpinScanStep = SpinScanStep()
    cube_scan: SpinScanStep = SpinScanStep()


class InitialSettings(Model):
    """Initial calibration (paper §IV-A)."""

    bin_deg: Positive = 0.02
    line_tolerance: Positive = Field(0.002, description="max RMS of a line segment, metres")
    min_segment_points: int = Field(8, gt=2)
    angle_tolerance_deg: Positive = 10.0
    length_tolerance: Positive = Field(0.3, description="relative tolerance on CAD lengths")


class OptimizerSettings(Model):
    """SciPy least_squares (TRF) settings shared by the fine-tuning strategies."""

    translation_bound: Positive = 0.020
    rotation_bound_deg: Positive = 2.0
    xtol: Positive = 1e-12
    ftol: Positive = 1e-10


class ShapeSettings(OptimizerSettings):
    """Shape-constrained fine-tuning (paper §III-B-1, §IV-B)."""

    max_nfev: int = Field(100, gt=0)
    segment_margin: NonNegative = 0.010
    outlier_radius: Positive = 0.001
    outlier_neighbours: int = Field(8, ge=0)


class PeriodicitySettings(OptimizerSettings):
    """Periodicity-constrained fine-tuning (paper §III-B-2, §IV-C) and its robustness schedule."""

    max_nfev: int = Field(10, gt=0, description="evaluations per inner solve")
    max_outer: int = Field(15, gt=0)
    match_distance: Positive = 0.20
    normal_neighbours: int = Field(50, gt=2)
    coarse_to_fine: bool = True
    gauge: Literal["platter", "ty"] = "platter"
    ry_bound_deg: Positive = Field(
        2.5, description="ry bound around its start (never re-centred): set-B starts are 2° off"
    )


class ShapeOptions(Model):
    """``calibration.options.shape``: the built-in shape strategy's choices (docs/algorithms.md)."""

    box: Literal["upright", "minimal"] = Field(
        "upright",
        description="upright: calstation's box standing on the platter; minimal: the paper's",
    )
    estimate_ry: bool = Field(True, description="estimate ry (false: hold it at its start)")
    coarse: bool = Field(True, description="coarse periodicity alignment on the cube scan first")


class SigmaLimits(Model):
    """``calibration.max_sigma``: the largest 1σ a fine-tuning may report per parameter.

    A result with a larger σ is refused (the data do not determine that parameter well
    enough), with a message that names the parameter and what to do. ty is the gauge along the
    axis and has no limit. Lengths in metres, angles in degrees.
    """

    tx: Positive = 0.0005
    tz: Positive = 0.0005
    ry_deg: Positive = 0.1
    rz_deg: Positive = 0.05


class CalibrationSettings(Model):
    """Which fine-tuning strategy to run, and each stage's settings."""

    strategy: str = "periodicity"
    initial: InitialSettings = InitialSettings()
    shape: ShapeSettings = ShapeSettings()
    periodicity: PeriodicitySettings = PeriodicitySettings()
    max_sigma: SigmaLimits = SigmaLimits()
    options: dict[str, dict[str, Any]] = Field(
        default_factory=dict, description="settings of plugin strategies, by strategy name"
    )


class QALimits(Model):
    """Pass/fail limits of the cube check and drift alarms (metres and degrees)."""

    edge_error: Positive = 0.0010
    obb_edge_error: Positive = 0.0060
    flatness_rms: Positive = 0.0015
    perpendicularity_deg: Positive = 0.5
    twist_deg: Positive = Field(
        0.1, description="largest ry correction the cube's side faces may ask for (degrees)"
    )
    drift_translation: Positive = 0.002
    drift_rotation_deg: Positive = 0.2
    drift_fails: bool = Field(
        False, description="drift beyond the limits fails the run (default: a warning only)"
    )


# --- the recipe ----------------------------------------------------------------------------
class Recipe(Model):
    """A whole recipe."""

    name: str = Field(min_length=1)
    description: str = ""
    version: int = Field(1, ge=1)
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

    After the field checks, :func:`cross_field_problems` runs the checks that relate fields to each
    other (and mesh files to ``base_dir``, the recipe's folder, when given).
    """
    try:
        data = yaml.safe_load(text)
        node = yaml.compose(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{source}:{mark.line + 1}" if mark is not None else source
        problem = getattr(exc, "problem", None) or str(exc)
        raise RecipeError(f"{where}: not valid YAML: {problem}") from None
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
            msg = err["msg"]
            if err["type"] == "extra_forbidden":
                msg = "unknown key"
            problems.append(f"{where}: {_format_loc(loc)}: {msg}")
        raise RecipeError("invalid recipe:\n  " + "\n  ".join(problems)) from None
    cross = cross_field_problems(recipe, base_dir)
    if cross:
        raise RecipeError(_format_problems(cross, node, source))
    return recipe


Problem = tuple[tuple[int | str, ...], str]
"""A validation problem: the field path in the recipe and what is wrong."""


def _format_problems(problems: list[Problem], node: yaml.Node | None, source: str) -> str:
    lines = []
    for loc, msg in problems:
        line = _line_of(node, loc)
        where = f"{source}:{line}" if line else source
        lines.append(f"{where}: {_format_loc(loc)}: {msg}")
    return "invalid recipe:\n  " + "\n  ".join(lines)


def _footprint_radius(geometry: Any) -> float:
    """Radius (m) of the circle around the fixture's own centre that holds its base outline."""
    if isinstance(geometry, CubeGeometry):
        return geometry.edge / math.sqrt(2.0)
    if isinstance(geometry, PyramidGeometry):
        return geometry.base / math.sqrt(2.0)
    if isinstance(geometry, PrismGeometry):
        return 0.5 * math.hypot(geometry.edge, geometry.depth)
    if isinstance(geometry, FrustumGeometry):
        if geometry.polygon is not None:
            return max(math.hypot(y, z) for y, z in geometry.polygon)
        return geometry.circumradius
    return 0.0


def cross_field_problems(recipe: Recipe, base_dir: Path | None = None) -> list[Problem]:
    """Checks that relate fields to each other; each problem names the field it is about.

    Fixtures must stand on the platter; mesh files must exist (relative to ``base_dir``); the
    spin target's facets must be flatter than the lidar's pitch (else they are seen in one half-turn
    only); the simulated lidar's range window must be ordered; explicit true extrinsics name only
    tx..rz; the encoder latency must be plausible.
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
        mesh = getattr(geometry, "mesh", None)
        if mesh:
            path = Path(mesh)
            if not path.is_absolute() and base_dir is not None:
                path = base_dir / path
            if (base_dir is not None or path.is_absolute()) and not path.is_file():
                problems.append(((*loc, "mesh"), f"mesh file not found: {path}"))
        offset = getattr(geometry, "offset", (0.0, 0.0))
        reach = math.hypot(*offset) + _footprint_radius(geometry)
        if reach > radius + 1e-9:
            problems.append(
                (
                    (*loc, "offset"),
                    f"the fixture reaches {reach * 1000:.0f} mm from the axis, off the platter "
                    f"(radius {radius * 1000:.0f} mm)",
                )
            )
    lt = fixtures.static_target
    if lt.base_length <= lt.wall_thickness:
        problems.append(
            (("fixtures", "static_target", "base_length"), "must be longer than wall_thickness")
        )
    sim = recipe.simulation
    if sim is not None:
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
        if sim.lidar.range_min >= sim.lidar.range_max:
            problems.append(
                (("simulation", "lidar", "range_min"), "must be smaller than range_max")
            )
        if sim.truth.H is not None:
            unknown = sorted(set(sim.truth.H) - {"tx", "ty", "tz", "rx", "ry", "rz"})
            if unknown:
                problems.append(
                    (
                        ("simulation", "truth", "H", unknown[0]),
                        f"unknown parameter {unknown[0]!r}; expected tx, ty, tz, rx, ry, rz",
                    )
                )
    shape_options = recipe.calibration.options.get("shape")
    if shape_options is not None:
        try:
            ShapeOptions.model_validate(shape_options)
        except ValidationError as exc:
            for err in exc.errors():
                problems.append((("calibration", "options", "shape", *err["loc"]), err["msg"]))
    if abs(recipe.station.encoder.latency_s) > 1.0:
        problems.append(
            (("station", "encoder", "latency_s"), "implausible latency (more than 1 s)")
        )
    return problems


def plugin_problems(recipe: Recipe) -> list[Problem]:
    """Checks against the installed plugins: drivers and strategies named must be registered."""
    from . import plugins

    problems: list[Problem] = []
    registered = plugins.drivers()
    for kind in plugins.DRIVER_KINDS:
        name = getattr(recipe.station, kind).driver
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
    from .strategies import recipe_option_problems

    problems += recipe_option_problems(recipe, strategies)
    return problems


def check_plugins(loaded: LoadedRecipe) -> None:
    """Raise :class:`RecipeError` (field and line of each problem) if a driver or strategy the
    recipe names is not installed."""
    problems = plugin_problems(loaded.recipe)
    if problems:
        source = str(loaded.path) if loaded.path is not None else "<recipe>"
        raise RecipeError(_format_problems(problems, yaml.compose(loaded.text), source))


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

    Raises :class:`RecipeError` if the file is missing, is not YAML, or fails validation; the
    message names the file, each field and its line.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise RecipeError(f"{p}: recipe file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise RecipeError(f"{p}: cannot read recipe: {exc}") from None
    return LoadedRecipe(parse_recipe(text, str(p), p.parent), p, text)
