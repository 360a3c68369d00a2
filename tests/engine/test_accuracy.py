"""Acceptance of the calibration engine on the simulated station (slow; run with -m slow).

The paper's nine scenarios (range 1.00/1.25/1.50 m × pitch 30/45/60°), against the simulator's
true H with the DESIGN §8 metrics, and ten set-A starts (±100 mm, ±1°, ty fixed) in two
scenarios. Two seeds: seed 1 draws a true ry of +0.008°, seed 4 one of −0.355° (ry is the
weakly observable parameter, and the initial calibration assumes ry = 0).

The shape strategy runs on both seeds: its ry comes from the flatness of the cube's faces
(docs/algorithms.md), so seed 4's true ry must be found, not assumed.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from calstation.engine.cube import check_cube
from calstation.engine.frames import Extrinsics
from calstation.engine.initial import initial_calibration
from calstation.engine.metrics import axis_errors, reconstruction_distortion
from calstation.plugins.cost_strategies import PeriodicityStrategy, ShapeStrategy
from calstation.recipes import load_recipe
from calstation.recordings.reader import read_recording

pytestmark = pytest.mark.slow

SCENARIOS = [(r, p) for r in (1.0, 1.25, 1.5) for p in (30.0, 45.0, 60.0)]
RECIPE = "recipes/sim-periodicity.yaml"


def _setup(sim_run, range_m: float, pitch_deg: float, seed: int = 1):
    run = sim_run(range_m=range_m, pitch_deg=pitch_deg, seed=seed)
    recipe = load_recipe(RECIPE).recipe
    static = read_recording(run["static"])
    truth = static.truth
    assert truth is not None
    initial = initial_calibration(static, recipe.fixtures.static_target, recipe.calibration.initial)
    return run, recipe, truth, initial


def _periodicity_ok(H: Extrinsics, truth: Extrinsics) -> dict[str, float]:
    e = axis_errors(H, truth)
    assert e["axis_offset_m"] <= 0.5e-3, e
    assert math.degrees(e["axis_angle_rad"]) <= 0.1, e
    assert abs(math.degrees(e["rz_error"])) <= 0.05, e
    return e


@pytest.mark.parametrize("seed", [1, 4])
@pytest.mark.parametrize(("range_m", "pitch_deg"), SCENARIOS)
def test_nine_scenarios(sim_run, range_m: float, pitch_deg: float, seed: int) -> None:
    run, recipe, truth, initial = _setup(sim_run, range_m, pitch_deg, seed)
    err = initial.H.as_vector() - truth.as_vector()
    assert np.all(np.abs(err[:3]) <= 0.1) and np.all(np.abs(np.degrees(err[3:])) <= 1.0)

    per = PeriodicityStrategy().run(read_recording(run["spin"]), initial.H, recipe)
    _periodicity_ok(per.H, truth)
    cube = read_recording(run["cube"])
    dist = reconstruction_distortion(cube, per.H, truth)
    assert dist["rms_m"] <= 0.5e-3
    check = check_cube(cube, per.H, recipe.fixtures.qa_cube, recipe.qa)
    assert check.edge_error <= 0.5e-3, check.to_dict()


def _shape_ok(sim_run, range_m: float, pitch_deg: float, seed: int) -> None:
    run, recipe, truth, initial = _setup(sim_run, range_m, pitch_deg, seed)
    shape = ShapeStrategy().run(read_recording(run["cube"]), initial.H, recipe)
    e = axis_errors(shape.H, truth)
    assert e["axis_offset_m"] <= 2e-3, e
    assert math.degrees(e["axis_angle_rad"]) <= 0.3, e


@pytest.mark.parametrize("seed", [1, 4])
@pytest.mark.parametrize(("range_m", "pitch_deg"), SCENARIOS)
def test_shape_nine_scenarios(sim_run, range_m: float, pitch_deg: float, seed: int) -> None:
    _shape_ok(sim_run, range_m, pitch_deg, seed)


@pytest.mark.parametrize(("range_m", "pitch_deg"), [(1.25, 45.0), (1.0, 60.0)])
def test_ten_set_a_starts(sim_run, range_m: float, pitch_deg: float) -> None:
    run, recipe, truth, initial = _setup(sim_run, range_m, pitch_deg)
    spin = read_recording(run["spin"])
    rng = np.random.default_rng(2026)
    for _ in range(10):
        u = rng.uniform(-1.0, 1.0, 4)
        start = initial.H.with_(
            tx=initial.H.tx + 0.1 * u[0],
            tz=initial.H.tz + 0.1 * u[1],
            ry=initial.H.ry + math.radians(u[2]),
            rz=initial.H.rz + math.radians(u[3]),
        )
        res = PeriodicityStrategy().run(spin, start, recipe)
        _periodicity_ok(res.H, truth)
