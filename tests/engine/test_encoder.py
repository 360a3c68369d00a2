"""The turntable encoder's angle error (calstation.engine.encoder): how each fixture's fit says
it follows it, checked against the simulator, and how the combination carries it."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from calstation.engine.encoder import HARMONICS, basis, coefficient_sigma
from calstation.engine.fusion import Estimate, consistent, fuse
from calstation.engine.rangemodel import ESTIMATED_NAMES, RangeModel
from calstation.recipes import load_recipe
from tests.support.rangemodel import sensor_recipe

ENCODER = {"eccentricity_deg": 0.1, "eccentricity_phase_deg": 30.0,
           "second_harmonic_deg": 0.03, "second_harmonic_phase_deg": 70.0}
"""An encoder error five times sim-realistic's, at phases that give all four coefficients."""
OFFSET = 0.003
"""The lidar's range offset in both scenes (m)."""


def _coefficients() -> np.ndarray:
    """ENCODER's coefficients a₁, b₁, a₂, b₂ (rad): e₁·sin(φ + p₁) = e₁cos p₁·sin φ +
    e₁sin p₁·cos φ."""
    e1, p1 = math.radians(0.1), math.radians(30.0)
    e2, p2 = math.radians(0.03), math.radians(70.0)
    return np.array([e1 * math.cos(p1), e1 * math.sin(p1), e2 * math.cos(p2), e2 * math.sin(p2)])


def test_the_coefficients_are_those_of_the_simulated_error() -> None:
    phi = np.linspace(-math.pi, math.pi, 50)
    e = (math.radians(0.1) * np.sin(phi + math.radians(30.0))
         + math.radians(0.03) * np.sin(2 * phi + math.radians(70.0)))
    assert np.allclose(basis(np.cos(phi), np.sin(phi)) @ _coefficients(), e, atol=1e-12)


@pytest.fixture(scope="module")
def scenes(sim_run: Any, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """One station simulated twice, with the same seed: with ENCODER's error and without it."""
    from calstation.pipeline import turned
    from calstation.recordings.reader import read_recording

    folder = tmp_path_factory.mktemp("encoder")
    out: dict[str, Any] = {}
    for name, sensor in (("exact", {"range": {"offset": OFFSET}}),
                         ("eccentric", {"range": {"offset": OFFSET}, "encoder": ENCODER})):
        run = sim_run(seed=5, recipe=sensor_recipe(folder, sensor, f"{name}.yaml"))
        out[name] = {k: turned(read_recording(run[k])) for k in ("spin", "cube")}
    out["recipe"] = load_recipe(folder / "exact.yaml").recipe
    return out


def _moved(before: Any, after: Any, names: tuple[str, ...]) -> np.ndarray:
    return np.array([getattr(after.H, n) - getattr(before.H, n) for n in names])


def _predicted(directions: dict[str, dict[str, float]], names: tuple[str, ...]) -> np.ndarray:
    u = _coefficients()
    return np.array([sum(directions[h][n] * u[j] for j, h in enumerate(HARMONICS))
                     for n in names])


def test_the_cube_fit_moves_as_it_says_it_follows_the_encoder(scenes: dict[str, Any]) -> None:
    """The known-size cube fit with the range model, on the same returns read at angles with
    and without the encoder's error: it moves by what its ``encoder_direction`` predicts."""
    from calstation.engine.cubefit import known_size_fit

    recipe = scenes["recipe"]
    truth = scenes["exact"]["cube"].recording.truth
    fits = [known_size_fit(scenes[k]["cube"].prepared, truth, recipe.fixtures.qa_cube,
                           platter_radius=recipe.fixtures.platter.radius, range_model="offset",
                           start_range=RangeModel(offset=OFFSET), encoder=True)
            for k in ("exact", "eccentric")]
    names = ("tx", "ty", "tz", "rz")
    moved = _moved(fits[0], fits[1], names)
    predicted = _predicted(fits[1].encoder_direction or {}, names)
    # the error moves tz by tens of micrometres: the prediction holds it to a few
    assert np.abs(moved).max() > 20e-6, moved
    assert np.allclose(moved, predicted, rtol=0.1, atol=5e-6), (moved, predicted)


def test_the_spin_target_moves_as_it_says_it_follows_the_encoder(
    scenes: dict[str, Any],
) -> None:
    """The periodicity fine-tuning's last stage from the true H, its range offset held: it
    moves by what ``diagnostics["follows_encoder"]`` predicts."""
    from calstation.engine.periodicity import periodicity_fine_tune_scan

    recipe = scenes["recipe"]
    truth = scenes["exact"]["spin"].recording.truth
    results = [periodicity_fine_tune_scan(scenes[k]["spin"].prepared, truth,
                                          platter_radius=recipe.fixtures.platter.radius,
                                          warm=True, range_model="offset",
                                          start_range=RangeModel(offset=OFFSET), encoder=True)
               for k in ("exact", "eccentric")]
    names = ("tx", "tz", "rz")
    moved = _moved(results[0], results[1], names)
    predicted = _predicted(results[1].diagnostics["follows_encoder"], names)
    assert np.abs(moved).max() > 10e-6, moved
    assert np.allclose(moved, predicted, rtol=0.25, atol=5e-6), (moved, predicted)


def test_the_shape_strategys_sigma_carries_the_encoder(scenes: dict[str, Any]) -> None:
    """The shape strategy (the cube alone) on the eccentric scene: its known-size fit says how
    it follows the encoder, and with the encoder's accuracy (0.13°, what ENCODER's harmonics
    add to at most) carried, every parameter is within 3σ of the physical H; without, tz is
    not (the error moves it ~0.2 mm at σ ~5 µm)."""
    from calstation.engine.joint import with_encoder_error
    from calstation.engine.metrics import axis_errors
    from calstation.engine.shape import shape_fine_tune_points

    recipe = scenes["recipe"]
    turned = scenes["eccentric"]["cube"]
    truth = turned.recording.truth
    scan = turned.prepared
    result = shape_fine_tune_points(
        scan.p_L, scan.phi, truth, recipe.fixtures.qa_cube,
        platter_radius=recipe.fixtures.platter.radius, scan=scan, range_model="offset",
        encoder=True)
    assert set(result.diagnostics["follows_encoder"]) == set(HARMONICS)
    names = ("tx", "tz", "ry", "rz")
    errors = axis_errors(result.H, truth)
    assert any(abs(errors[f"{n}_error"]) > 3 * result.sigma[n] for n in names), errors
    widened = with_encoder_error(result, math.radians(0.13))
    for n in names:
        assert abs(errors[f"{n}_error"]) <= 3 * widened.sigma[n], (n, errors, widened.sigma)


MM_PER_DEGREE = 1e-3 * 180.0 / math.pi
"""m/rad per mm/°."""
SPIN = {h: {n: v * MM_PER_DEGREE for n, v in d.items()} for h, d in {
    "encoder_sin1": {"tx": 0.048, "tz": 0.49}, "encoder_cos1": {"tx": -0.097, "tz": -0.64},
    "encoder_sin2": {"tx": 0.012, "tz": 0.20}, "encoder_cos2": {"tx": 0.144, "tz": -0.13}}.items()}
CUBE = {"encoder_sin1": {"tx": -0.0021, "tz": 0.078},
        "encoder_cos1": {"tx": -0.0092, "tz": 0.023},
        "encoder_sin2": {"tx": -0.0060, "tz": 0.0071},
        "encoder_cos2": {"tx": -0.0042, "tz": -0.037}}
"""How the spin target's and the cube's tx and tz follow each coefficient (m/rad): a run of
recipes/sim-realistic.yaml on the simulator."""


def _estimate(directions: dict[str, dict[str, float]], sigma: float) -> Estimate:
    """An estimate of (tx, tz) that is off by exactly what sim-realistic's encoder error
    (0.02° once per turn, 0.005° twice, phases 0) moves it, with a σ of ``sigma``."""
    u = np.radians([0.02, 0.0, 0.005, 0.0])
    vector = np.zeros(len(ESTIMATED_NAMES))
    for n in ("tx", "tz"):
        vector[ESTIMATED_NAMES.index(n)] = sum(directions[h][n] * u[j]
                                                for j, h in enumerate(HARMONICS))
    return Estimate(vector, ("tx", "tz"), np.diag([sigma**2, sigma**2]), {})


def test_the_combination_covers_what_the_encoder_moves() -> None:
    """sim-realistic's encoder moved the cube's tz 28 µm at σ 4 µm (7σ): combined as they are,
    the result is beyond 3σ; with the encoder's stated accuracy (0.025°) carried, the two
    agree and the result is within 3σ of the truth (0)."""
    spin, cube = _estimate(SPIN, 9e-6), _estimate(CUBE, 4e-6)
    naive = fuse(spin, cube)
    assert abs(naive.vector[ESTIMATED_NAMES.index("tz")]) > 3 * naive.sigma["tz"]
    sigma = coefficient_sigma(math.radians(0.025))
    fused = fuse(spin.with_encoder(SPIN, sigma), cube.with_encoder(CUBE, sigma))
    assert consistent(fused)
    for n in ("tx", "tz"):
        assert abs(fused.vector[ESTIMATED_NAMES.index(n)]) <= 3 * fused.sigma[n], n
    assert spin.with_encoder(SPIN, 0.0) is spin


def test_without_the_range_model_the_encoder_widens_the_spin_targets_sigma() -> None:
    """Without the lidar's range model nothing tells the encoder's error apart: what it may do
    (``follows_encoder`` × each coefficient's σ) is added to the spin target's covariance."""
    from calstation.engine.frames import Extrinsics
    from calstation.engine.joint import with_encoder_error
    from calstation.engine.result import CalibrationResult

    names = ["tx", "tz"]
    result = CalibrationResult(
        H=Extrinsics.from_vector(np.zeros(6)), sigma={"tx": 9e-6, "tz": 1e-5}, cost=0.0,
        iterations=1, strategy="periodicity",
        diagnostics={"covariance": {"parameters": names,
                                    "matrix": np.diag([9e-6**2, 1e-5**2]).tolist()},
                     "follows_encoder": SPIN})
    accuracy = math.radians(0.025)
    widened = with_encoder_error(result, accuracy)
    sigma_c = coefficient_sigma(accuracy)
    for n, own in (("tx", 9e-6), ("tz", 1e-5)):
        extra = sum((SPIN[h][n] * sigma_c) ** 2 for h in HARMONICS)
        assert math.isclose(widened.sigma[n], math.sqrt(own**2 + extra), rel_tol=1e-12)
    assert with_encoder_error(widened, accuracy) is widened
    assert with_encoder_error(result, 0.0) is result
