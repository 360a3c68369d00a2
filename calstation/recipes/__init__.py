"""Recipes: one YAML file per station and fixture set, parsed into typed models.

Lengths are metres; angles carry their unit in the field name (``_deg`` or ``_rad``). Unknown keys
are errors. :func:`load_recipe` reports every problem with the YAML field path and line.

One module per section or step of the work: :mod:`~calstation.recipes.station`,
:mod:`~calstation.recipes.fixtures`, :mod:`~calstation.recipes.simulation`,
:mod:`~calstation.recipes.steps` and :mod:`~calstation.recipes.calibration` hold the sections'
models (the engine's settings nested where the engine takes them,
:mod:`calstation.engine.settings`); :mod:`~calstation.recipes.recipe` the whole recipe;
:mod:`~calstation.recipes.load` reading it, :mod:`~calstation.recipes.validation` the checks that
relate fields to each other and :mod:`~calstation.recipes.problems` how a problem is located and
worded; :mod:`~calstation.recipes.catalog` the recipes calstation ships. The public names are
importable from the package, as below.

Recipes know nothing of plugins: the checks against the installed drivers and strategies are the
plugin layer's, :func:`calstation.plugins.recipe_checks.check_plugins`.
"""

from __future__ import annotations

from calstation.engine.settings import (  # nested in a recipe; importable from here too
    DEFAULT_PLATTER_RADIUS as DEFAULT_PLATTER_RADIUS,
    AccuracySettings as AccuracySettings,
    Coordinate as Coordinate,
    CubeGeometry as CubeGeometry,
    InitialSettings as InitialSettings,
    LTargetGeometry as LTargetGeometry,
    OptimizerSettings as OptimizerSettings,
    PeriodicitySettings as PeriodicitySettings,
    PlatterGeometry as PlatterGeometry,
    QALimits as QALimits,
    ShapeOptions as ShapeOptions,
    ShapeSettings as ShapeSettings,
    SigmaLimits as SigmaLimits,
    Yaw as Yaw,
)
from calstation.recipes.base import Model as Model
from calstation.recipes.calibration import (
    BUILTIN_OPTIONS as BUILTIN_OPTIONS,
    CalibrationSettings as CalibrationSettings,
    PeriodicityOptions as PeriodicityOptions,
    options_problems as options_problems,
)
from calstation.recipes.catalog import (
    SHIPPED_DIR as SHIPPED_DIR,
    shipped_recipe as shipped_recipe,
    shipped_recipes as shipped_recipes,
)
from calstation.recipes.fixtures import (
    MAX_MESH_BYTES as MAX_MESH_BYTES,
    POLYGON_MIN_SPACING as POLYGON_MIN_SPACING,
    POLYGON_MIN_TURN_DEG as POLYGON_MIN_TURN_DEG,
    FixtureGeometry as FixtureGeometry,
    Fixtures as Fixtures,
    FrustumGeometry as FrustumGeometry,
    MeshGeometry as MeshGeometry,
    PrismGeometry as PrismGeometry,
    PyramidGeometry as PyramidGeometry,
    frustum_outline as frustum_outline,
    frustum_problems as frustum_problems,
    mesh_footprint as mesh_footprint,
    polygon_problems as polygon_problems,
)
from calstation.recipes.load import (
    MAX_RECIPE_BYTES as MAX_RECIPE_BYTES,
    load_recipe as load_recipe,
    parse_recipe as parse_recipe,
)
from calstation.recipes.problems import Problem as Problem
from calstation.recipes.recipe import LoadedRecipe as LoadedRecipe, Recipe as Recipe
from calstation.recipes.simulation import (
    BackgroundModel as BackgroundModel,
    EncoderModel as EncoderModel,
    LidarModel as LidarModel,
    PlacementError as PlacementError,
    SensorModel as SensorModel,
    SimulationConfig as SimulationConfig,
    TruthConfig as TruthConfig,
    TurntableModel as TurntableModel,
)
from calstation.recipes.station import (
    DriverConfig as DriverConfig,
    EncoderConfig as EncoderConfig,
    StationConfig as StationConfig,
)
from calstation.recipes.steps import (
    SpinScanStep as SpinScanStep,
    StaticScanStep as StaticScanStep,
    Steps as Steps,
)
from calstation.recipes.validation import (
    MAX_SCAN_ENCODER_SAMPLES as MAX_SCAN_ENCODER_SAMPLES,
    MAX_SCAN_LINES as MAX_SCAN_LINES,
    MAX_SCAN_POINTS as MAX_SCAN_POINTS,
    MAX_SCAN_SECONDS as MAX_SCAN_SECONDS,
    PARAM_NAMES as PARAM_NAMES,
    PREFLIGHT_RAMP_S as PREFLIGHT_RAMP_S,
    SECOND_PASS_CONTRAST as SECOND_PASS_CONTRAST,
    cross_field_problems as cross_field_problems,
)
