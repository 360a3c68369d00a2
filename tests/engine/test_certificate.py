"""The lidar's range offset from its certificate combined with the station's measurement of it:
the update's arithmetic against the Gaussian product it is, and a simulated lidar 4 mm long
whose certificate narrows H along its boresight, or refuses the run when it is another's."""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np
import pytest
import yaml

from calstation.engine.certificate import Certificate, with_certificate
from calstation.engine.frames import Extrinsics
from calstation.engine.result import CalibrationResult
from tests.support.rangemodel import run_scans, sensor_recipe

NAMES = ["tx", "ty", "tz", "ry", "rz", "range_offset"]


def _measured(offset: float = 0.0021) -> CalibrationResult:
    """A result whose ty and range offset are strongly correlated (as on the station: both move
    the cube along the rays), with a bias bound in ty's σ beyond its covariance."""
    rng = np.random.default_rng(4)
    A = rng.normal(size=(6, 6)) * 1e-5
    C = A @ A.T + np.diag([1e-9, 4e-8, 1e-9, 1e-8, 1e-8, 4e-8])
    C[1, 5] = C[5, 1] = 0.95 * math.sqrt(C[1, 1] * C[5, 5])
    sigma = {n: math.sqrt(C[k, k]) for k, n in enumerate(NAMES[:5])}
    sigma["rx"] = math.nan
    sigma["ty"] = math.hypot(sigma["ty"], 3e-5)  # a bias bound in quadrature
    H = Extrinsics(0.01, 1.2, 0.02, 0.0, 0.6, -0.7)
    return CalibrationResult(
        H, sigma, 0.0, 1, "shape",
        diagnostics={"covariance": {"parameters": NAMES, "matrix": C.tolist()}},
        range_offset=offset, sigma_range_offset=math.sqrt(C[5, 5]),
    )


def test_the_certificate_is_combined_as_the_product_of_the_two_gaussians() -> None:
    result = _measured()
    C = np.asarray(result.diagnostics["covariance"]["matrix"])
    cert = Certificate(offset=0.0022, sigma=5e-5)
    combined, failure = with_certificate(result, cert)
    assert failure is None
    # the joint Gaussian's information plus the certificate's on b: the product's mean and
    # covariance
    info = np.linalg.inv(C)
    info[5, 5] += 1 / cert.sigma**2
    x0 = np.array([*result.H.as_vector()[[0, 1, 2, 4, 5]], result.range_offset])
    eta = np.linalg.inv(C) @ x0
    eta[5] += cert.offset / cert.sigma**2
    cov = np.linalg.inv(info)
    mean = cov @ eta
    got = np.array([*combined.H.as_vector()[[0, 1, 2, 4, 5]], combined.range_offset])
    assert got == pytest.approx(mean, abs=1e-12)
    assert np.asarray(combined.diagnostics["covariance"]["matrix"]) == pytest.approx(cov, rel=1e-9)
    assert combined.sigma_range_offset == pytest.approx(math.sqrt(cov[5, 5]))
    assert combined.sigma["tz"] == pytest.approx(math.sqrt(cov[2, 2]))
    # the bias bound beyond the covariance stays in ty's σ
    assert combined.sigma["ty"] == pytest.approx(math.sqrt(cov[1, 1] + 3e-5**2))
    assert combined.sigma["ty"] < result.sigma["ty"]
    assert combined.H.rx == result.H.rx and combined.diagnostics["certificate"]["combined"]


def test_a_judged_result_carrying_an_unmeasured_scale_is_combined_too() -> None:
    """After the judgement a result's covariance carries the scale error it did not measure
    (rangemodel.with_unmeasured_scale, as `calstation plan` combines a certificate): that term
    stays a covariance column, not an estimate."""
    from calstation.engine.rangemodel import with_unmeasured_scale

    result = _measured()
    sigma, record = with_unmeasured_scale(result.H.t, result.sigma,
                                          result.diagnostics["covariance"], 1e-4)
    judged = replace(result, sigma=sigma, diagnostics={"covariance": record})
    combined, failure = with_certificate(judged, Certificate(0.0021, 2e-5))
    assert failure is None and combined.range_scale is None
    assert "range_scale" not in combined.sigma
    names = combined.diagnostics["covariance"]["parameters"]
    assert "range_scale" in names and combined.sigma_range_offset < 2e-5
    assert combined.sigma["ty"] < judged.sigma["ty"]


def test_a_certificate_apart_beyond_chance_refuses_and_moves_nothing() -> None:
    result = _measured()
    far = Certificate(offset=result.range_offset - 5 * result.sigma_range_offset, sigma=1e-5)
    kept, failure = with_certificate(result, far)
    assert failure is not None and "certificate says" in failure and "+2.100" in failure
    assert kept.H == result.H and kept.range_offset == result.range_offset
    assert kept.diagnostics["certificate"]["combined"] is False
    # within chance (3 σ apart: p = 2.7e-3 > 1e-3) it is combined
    near = Certificate(offset=result.range_offset - 3 * result.sigma_range_offset, sigma=1e-9)
    assert with_certificate(result, near)[1] is None


def test_a_result_that_did_not_measure_the_offset_is_left_as_it_is() -> None:
    cert = Certificate(0.0, 1e-4)
    held = replace(_measured(), sigma_range_offset=math.nan)  # a spin target's alone
    assert with_certificate(held, cert) == (held, None)
    none = replace(_measured(), range_offset=None, sigma_range_offset=None)
    assert with_certificate(none, cert) == (none, None)
    assert with_certificate(_measured(), None) == (_measured(), None)


def _calibrated(offset_run: Any, certificate: dict[str, float]) -> Any:
    from calstation import plugins
    from calstation.pipeline import Scans, calibrate, turned
    from calstation.recipes import parse_recipe
    from calstation.recordings.reader import read_recording

    *_, path = offset_run
    data = yaml.safe_load(path.read_text())
    data["calibration"]["range_offset_certificate"] = certificate
    recipe = parse_recipe(yaml.safe_dump(data), str(path))
    run = offset_run[0]
    scans = Scans(spin=turned(read_recording(run["spin"])), static=read_recording(run["static"]),
                  cube=turned(read_recording(run["cube"])))
    return calibrate(recipe, scans, plugins.strategy("periodicity"))


@pytest.fixture(scope="module")
def offset_run(sim_run: Any, tmp_path_factory: pytest.TempPathFactory) -> Any:
    """A simulated lidar 4 mm long (the range-model tests' run), calibrated without a
    certificate, and the recipe it was made with."""
    from calstation import plugins
    from calstation.pipeline import calibrate
    from calstation.recipes import load_recipe

    path = sensor_recipe(tmp_path_factory.mktemp("offset"), {"range": {"offset": 0.004}},
                   "offset.yaml")
    run = sim_run(recipe=path)
    done = calibrate(load_recipe(path).recipe, run_scans(run), plugins.strategy("periodicity"))
    return run, done, path


def test_the_lidars_certificate_narrows_h_along_its_rays_to_the_physical_truth(
    offset_run: Any,
) -> None:
    from calstation.engine.metrics import axis_errors
    from calstation.recordings.reader import read_recording

    run, alone, _ = offset_run
    truth = read_recording(run["cube"]).truth
    done = _calibrated(offset_run, {"offset": 0.00401, "sigma": 0.00002})
    result = done.result
    assert done.refused == [] and result.diagnostics["certificate"]["combined"]
    assert abs(result.range_offset - 0.004) <= 3 * result.sigma_range_offset
    assert result.sigma_range_offset < 0.25 * alone.result.sigma_range_offset
    e = axis_errors(result.H, truth)
    for name in ("tx", "ty", "tz", "ry", "rz"):
        assert abs(e[f"{name}_error"]) <= 3 * result.sigma[name], name
    # the offset and ty are one along the rays: ty and the axis follow b to the truth (on the
    # cube's measurement alone: ty 0.047 mm off, the axis 0.035 mm; with the certificate
    # 0.009 mm and 0.009 mm), and their σ narrow with b's
    assert abs(e["ty_error"]) < 0.02e-3 and e["axis_offset_m"] < 0.02e-3
    assert result.sigma["ty"] < alone.result.sigma["ty"]
    assert result.sigma["rz"] < alone.result.sigma["rz"]
    # the operator and the report are told where the offset came from
    from calstation.engine.joint import range_summary

    assert "with the lidar's certificate +4.010 ± 0.020 mm" in range_summary(result)
    # the reconstruction and the cube check use the combined H and range model
    assert done.cube_check is not None and done.cube_check.passed
    assert result.diagnostics["predicted_error"]["max_m"] \
        < alone.result.diagnostics["predicted_error"]["max_m"]


def test_a_certificate_of_another_lidar_refuses_the_run_naming_both_offsets(
    offset_run: Any,
) -> None:
    done = _calibrated(offset_run, {"offset": 0.0, "sigma": 0.00005})
    assert len(done.refused) == 1, done.refused
    assert "range offset reads +4.0" in done.refused[0] and "+0.000 ± 0.050 mm" in done.refused[0]
    assert not done.result.diagnostics["certificate"]["combined"]


def test_a_budget_the_measured_offset_keeps_out_of_reach_names_the_certificate(
    offset_run: Any,
) -> None:
    """The lidar 4 mm long calibrated on the cube alone predicts 0.10 mm; with its offset known,
    0.09 mm: against a budget between the two, the refusal says what a certificate would
    give."""
    from calstation.pipeline.judgement import judge, with_prediction
    from calstation.recipes import parse_recipe

    _, alone, path = offset_run
    data = yaml.safe_load(path.read_text())
    recipe = parse_recipe(yaml.safe_dump(data), str(path))
    measured = with_prediction(alone.result, recipe)[1].max_m
    from calstation.engine.observability import predict

    known = predict(alone.result, recipe.calibration.accuracy, recipe.fixtures.platter,
                    known=("range_offset",)).max_m
    assert known < 0.95 * measured, (known, measured)
    data["calibration"]["accuracy"] = {"max_error": (known + measured) / 2}
    _, refused = judge(alone.result, parse_recipe(yaml.safe_dump(data), str(path)))
    assert len(refused) == 1 and "calibration.range_offset_certificate" in refused[0], refused
    assert f"would be {known * 1e3:.3f} mm" in refused[0]
    # a budget the known offset would not meet either does not offer it
    data["calibration"]["accuracy"] = {"max_error": known * 0.9}
    _, refused = judge(alone.result, parse_recipe(yaml.safe_dump(data), str(path)))
    assert refused and "range_offset_certificate" not in refused[0]
