"""The checks of a recipe that relate fields to each other (:func:`cross_field_problems`).

Each problem names the field it is about; :func:`calstation.recipes.load.parse_recipe` reports
them with their YAML lines. The checks against the installed plugins (drivers, strategies, their
settings and options models) are the plugin layer's: :mod:`calstation.plugins.recipe_checks`.
"""

from __future__ import annotations

import math
from pathlib import Path

from calstation.recipes.calibration import BUILTIN_OPTIONS, options_problems
from calstation.recipes.fixtures import FrustumGeometry, fixture_problems
from calstation.recipes.problems import Problem
from calstation.recipes.recipe import Recipe
from calstation.recipes.steps import DEFAULT_MAX_REVOLUTIONS, SpinScanStep, Steps

MAX_SCAN_POINTS = 25_000_000
"""Most lidar points one simulated scan may produce (the default spin scan takes ~3.2 million)."""
MAX_SCAN_LINES = 200_000
"""Most lidar lines one simulated scan may produce (the default spin scan takes ~3200)."""
MAX_SCAN_ENCODER_SAMPLES = 20_000_000
"""Most encoder samples one simulated scan may produce."""
MIN_STATIC_LINES = 10
"""Fewest lines a static scan may take: the initial calibration takes the median range of each
azimuth bin over them, and fewer lines let a bin of mixed pixels or drop-outs through, which
splits the L-target's faces. On the simulated station (24 stations) 3 lines failed the initial
calibration once, 5 lines twice, 8 and 10 lines never (docs/recipes.md)."""
MAX_SCAN_SECONDS = 600.0
"""Longest scan a recipe may ask for (settle time plus the turns), seconds."""
PARAM_NAMES = ("tx", "ty", "tz", "rx", "ry", "rz")
"""The parameters ``simulation.truth.H`` may name."""
PREFLIGHT_RAMP_S = 1.5
"""How long the station's preflight lets the platter spin up before it counts
(:mod:`calstation.station.steps.preflight` takes it from here)."""


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
    named: list[tuple[tuple[int | str, ...], object]] = [
        (("fixtures", "static_target"), fixtures.static_target),
        (("fixtures", "spin_target"), fixtures.spin_target),
        (("fixtures", "qa_cube"), fixtures.qa_cube),
    ] + [(("fixtures", "demo", i), g) for i, g in enumerate(fixtures.demo)]
    for loc, geometry in named:
        problems += fixture_problems(loc, geometry, radius, base_dir)
    lt = fixtures.static_target
    if lt.base_length <= lt.wall_thickness:
        problems.append(
            (("fixtures", "static_target", "base_length"), "must be longer than wall_thickness")
        )
    problems += _simulation_problems(recipe)
    problems += _scan_problems(recipe)
    if (recipe.calibration.range_offset_certificate is not None
            and recipe.calibration.range_model == "none"):
        problems.append((("calibration", "range_offset_certificate"),
                         "needs a range model to combine with (calibration.range_model: offset "
                         "or offset+scale); with range_model: none the offset is taken as zero"))
    if (recipe.calibration.range_model == "offset+scale"
            and not fixtures.qa_cube.same_finish_as_platter):
        problems.append((("calibration", "range_model"), SCALE_NEEDS_ONE_FINISH))
    for name, model in BUILTIN_OPTIONS.items():
        if name in recipe.calibration.options:
            problems += options_problems(name, model, recipe.calibration.options[name])
    return problems


SCALE_NEEDS_ONE_FINISH = (
    "offset+scale measures the lidar's range scale error from the QA cube's height above the "
    "platter, a known length only when the lidar reads the two alike: a platter of another "
    "finish reads at another range (a few tenths of a millimetre between a dark and a light "
    "surface read as thousands of ppm of scale, and H's ty off by as much). State "
    "fixtures.qa_cube.same_finish_as_platter: true for a cube and platter top of one material "
    "and finish, or use range_model: offset, which carries the scale error as the uncertainty "
    "calibration.range_scale_sigma states (from the lidar's datasheet or certificate)")
"""Why ``range_model: offset+scale`` needs the cube and the platter of one finish."""


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


def _rates(recipe: Recipe) -> tuple[float, float, float, float]:
    """(simulated points/s, lines/s, encoder samples/s, spin-up rpm/s): what bounds a scan.
    The simulated scanner makes every point the model asks for; a real (or emulated) lidar
    streams at its own rate, bounded by the time only (rates 0)."""
    sim = recipe.simulation if recipe.station.lidar.driver == "sim" else None
    if sim is None:
        return 0.0, 0.0, 0.0, 60.0
    return (sim.lidar.points_per_line * sim.lidar.line_rate_hz, sim.lidar.line_rate_hz,
            sim.encoder.sample_rate_hz, sim.turntable.acceleration_rpm_s)


def _scan_seconds(recipe: Recipe, cfg: SpinScanStep, turns: float) -> float:
    """How long a scan of ``turns`` lasts, spin-up and settling included (s)."""
    accel = _rates(recipe)[3]
    scanning = turns * 60.0 / abs(cfg.rpm)
    if cfg.max_duration_s is not None:
        scanning = min(scanning, max(cfg.max_duration_s, cfg.revolutions * 60.0 / abs(cfg.rpm)))
    return cfg.settle_s + abs(cfg.rpm) / accel + scanning


def most_turns(recipe: Recipe, name: str) -> float:
    """The most turns the scan ``steps.<name>`` may take while its accuracy budget does not
    hold: its ``max_revolutions``, else :data:`DEFAULT_MAX_REVOLUTIONS` or fewer, as many
    as the limits of a scan (time, and simulated points, lines and encoder samples) allow —
    never fewer than its ``revolutions``."""
    cfg: SpinScanStep = getattr(recipe.steps, name)
    if cfg.max_revolutions is not None:
        return max(cfg.max_revolutions, cfg.revolutions)
    turns = DEFAULT_MAX_REVOLUTIONS
    while turns > cfg.revolutions and _turn_problems(recipe, name, cfg, turns, ""):
        turns -= 1.0
    return max(turns, cfg.revolutions)


def _turn_problems(
    recipe: Recipe, name: str, cfg: SpinScanStep, turns: float, field: str
) -> list[Problem]:
    """Why a scan of ``turns`` is more than a scan may be (time, simulated points, lines,
    encoder samples), reported at ``steps.<name>.<field>``."""
    rate, line_rate, sample_rate, _ = _rates(recipe)
    seconds = _scan_seconds(recipe, cfg, turns)
    where = ("steps", name, field)
    if seconds > MAX_SCAN_SECONDS:
        return [(where, f"{turns:g} turns at {cfg.rpm:g} rpm take {seconds:.0f} s, more than "
                        f"the {MAX_SCAN_SECONDS:g} s a scan may last")]
    if rate and seconds * rate > MAX_SCAN_POINTS:
        return [(where, f"{turns:g} turns at {cfg.rpm:g} rpm make about "
                        f"{seconds * rate / 1e6:.0f} million simulated points, more than the "
                        f"{MAX_SCAN_POINTS / 1e6:g} million a scan may hold: raise rpm or lower "
                        "the lidar's points_per_line × line_rate_hz")]
    if line_rate and seconds * line_rate > MAX_SCAN_LINES:
        return [(where, f"{turns:g} turns at {cfg.rpm:g} rpm make about "
                        f"{seconds * line_rate:,.0f} simulated lidar lines, more than the "
                        f"{MAX_SCAN_LINES:,} a scan may hold")]
    if sample_rate and seconds * sample_rate > MAX_SCAN_ENCODER_SAMPLES:
        return [(where, f"{turns:g} turns at {cfg.rpm:g} rpm make about "
                        f"{seconds * sample_rate / 1e6:.0f} million simulated encoder samples, "
                        f"more than the {MAX_SCAN_ENCODER_SAMPLES / 1e6:g} million a scan may "
                        "hold")]
    return []


def _scan_problems(recipe: Recipe) -> list[Problem]:
    """Scans must end: bounded in time, and (simulated) in the number of points."""
    problems: list[Problem] = []
    sim = recipe.simulation if recipe.station.lidar.driver == "sim" else None
    problems += _second_pass_problems(recipe.steps, recipe.station.turntable.driver)
    for name, cfg in _scans(recipe.steps):
        # the longest the scan may go on: its turns, or the turns asked for accuracy
        asked = cfg.max_revolutions is not None and cfg.max_revolutions > cfg.revolutions
        turns = cfg.max_revolutions if asked and cfg.max_revolutions is not None else (
            cfg.revolutions)
        field = "max_revolutions" if asked else "revolutions"
        problems += _turn_problems(recipe, name, cfg, turns, field)
    lines = recipe.steps.static_scan.lines
    if recipe.calibration.start == "l_target" and lines < MIN_STATIC_LINES:
        problems.append((("steps", "static_scan", "lines"),
                         f"{lines} line{'s' if lines != 1 else ''} are too few for the initial "
                         f"calibration, which needs at least {MIN_STATIC_LINES}: it takes the "
                         "median range of each azimuth bin over the lines, and fewer let mixed "
                         "pixels and drop-outs split the L-target's faces"))
    if sim is not None and lines * sim.lidar.points_per_line > MAX_SCAN_POINTS:
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

