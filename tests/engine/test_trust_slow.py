"""Trustworthy calibration across the condition matrix (slow; run with -m slow).

Conditions the default simulator does not produce: range noise 0.5–2 mm, no background, a
centred spin target, 180 and 360 lines/s. Each run is decided as the station decides it
(periodicity, its σ gate, the cube's twist combined into ry, the ry gate on the result;
shape gated on its own σ), and checked against the simulator's true H: either the step
refuses, or every parameter is within 3σ and the axis direction within the issue's threshold.
The full sweep of 120 runs is ``benchmarks/ry_sweep.py``.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import yaml

from calstation.engine.frames import Extrinsics
from calstation.engine.initial import initial_calibration
from calstation.engine.metrics import axis_errors
from calstation.engine.result import CalibrationResult
from calstation.pipeline import turned
from calstation.pipeline.stages import with_cube
from calstation.plugins.cost_strategies import PeriodicityStrategy, ShapeStrategy
from calstation.recipes import load_recipe
from calstation.recordings.reader import read_recording

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]


def _simulate(tmp_path: Path, *, noise: float, background: bool, offset: float, rate: float,
              scenario: tuple[float, float], seed: int) -> tuple[dict[str, Path], object]:
    from calstation_sim import simulate_run

    data = yaml.safe_load((REPO / "recipes/sim-periodicity.yaml").read_text())
    sim = data["simulation"]
    sim["lidar"].update(range_noise=noise, line_rate_hz=rate)
    sim["background"] = {"enabled": background}
    sim["truth"] = {"range": scenario[0], "pitch_deg": scenario[1]}
    sim["seed"] = seed
    data["fixtures"]["spin_target"]["offset"] = [offset, 0.0]
    path = tmp_path / "recipe.yaml"
    path.write_text(yaml.safe_dump(data))
    recipe = load_recipe(path).recipe
    return simulate_run(load_recipe(path), tmp_path, progress=False), recipe


# the thresholds on the axis direction of an accepted run: (p95 bound) per noise
DIRECTION_LIMIT_DEG = {0.0005: 0.1, 0.001: 0.1, 0.002: 0.2}


@pytest.mark.parametrize(
    ("noise", "background", "offset", "rate", "scenario", "seed"),
    [
        (0.0005, False, 0.0, 1000.0, (1.0, 30.0), 21),
        (0.001, False, 0.06, 1000.0, (0.9, 40.0), 22),
        (0.001, True, 0.0, 180.0, (1.25, 45.0), 23),
        (0.001, False, 0.06, 180.0, (1.5, 60.0), 24),
        (0.002, True, 0.06, 1000.0, (1.0, 45.0), 25),
        (0.002, False, 0.0, 1000.0, (0.9, 40.0), 26),
    ],
)
def test_periodicity_with_the_cube_is_within_3_sigma_accepted_or_not(
    tmp_path: Path, noise: float, background: bool, offset: float, rate: float,
    scenario: tuple[float, float], seed: int,
) -> None:
    """One turn, decided as the station decides it: the σ covers the error of the periodicity
    estimate and of its combination with the cube, whatever the budget decides; an accepted
    run's axis direction is within the issue's threshold, and every 0.5 mm run is accepted."""
    from calstation.pipeline.judgement import with_prediction

    run, recipe = _simulate(tmp_path, noise=noise, background=background, offset=offset,
                            rate=rate, scenario=scenario, seed=seed)
    static = read_recording(run["static"])
    truth = static.truth
    assert truth is not None
    initial = initial_calibration(static, recipe.fixtures.static_target, recipe.calibration.initial)
    fine = PeriodicityStrategy().run(read_recording(run["spin"]), initial.H, recipe)
    assert fine.diagnostics["range_noise_m"] == pytest.approx(noise, rel=0.2)
    _assert_covered(fine, truth)
    cubed = with_cube(recipe, PeriodicityStrategy(), fine, turned(read_recording(run["cube"])))
    outcome, failure = cubed.result, cubed.ry_failure
    assert failure is None or "ry" in failure, failure
    _assert_covered(outcome, truth)
    _, predicted = with_prediction(outcome, recipe)
    accepted = failure is None and predicted.max_m <= recipe.calibration.accuracy.max_error
    assert accepted or noise > 0.0005, (failure, predicted)
    if accepted:
        err = axis_errors(outcome.H, truth)
        assert math.degrees(err["axis_angle_rad"]) <= DIRECTION_LIMIT_DEG[noise], err


def _assert_covered(result: CalibrationResult, truth: Extrinsics) -> None:
    err = axis_errors(result.H, truth)
    sigma = result.sigma
    for name in ("tx", "tz", "ry", "rz"):
        assert abs(err[f"{name}_error"]) <= 3 * sigma[name], (name, err, sigma)


@pytest.mark.parametrize("rate", [180.0, 360.0, 1000.0])
def test_shape_at_1_mm_is_within_3_sigma(tmp_path: Path, rate: float) -> None:
    """The shape strategy at the default noise, one cube turn: it does not stop, its σ covers
    the error in every parameter, and an accepted result is within 0.5 mm and 0.1° of the
    axis."""
    from calstation.pipeline.judgement import with_prediction

    run, recipe = _simulate(tmp_path, noise=0.001, background=True, offset=0.06, rate=rate,
                            scenario=(1.25, 45.0), seed=31)
    static = read_recording(run["static"])
    truth = static.truth
    assert truth is not None
    initial = initial_calibration(static, recipe.fixtures.static_target, recipe.calibration.initial)
    result = ShapeStrategy().run(read_recording(run["cube"]), initial.H, recipe)
    _assert_covered(result, truth)
    err = axis_errors(result.H, truth)
    _, predicted = with_prediction(result, recipe)
    if predicted.max_m <= recipe.calibration.accuracy.max_error:
        assert err["axis_offset_m"] <= 0.5e-3, err
        assert math.degrees(err["axis_angle_rad"]) <= 0.1, err
