"""The predicted reconstruction error (calstation.engine.accuracy) against the distortion the
same uncertainty really causes, computed exactly from the simulator's kind of truth."""

from __future__ import annotations

import math

import numpy as np
import pytest

from calstation.engine.accuracy import (
    predicted_error,
    sightings,
    true_distortion,
    work_volume,
)
from calstation.engine.frames import Extrinsics, lidar_to_dynamic

H = Extrinsics(tx=0.01, ty=1.25, tz=-0.02, rx=0.0, ry=math.radians(0.2), rz=math.radians(-45))
RADIUS, HEIGHT = 0.2925, 0.15


def test_every_sighting_lies_in_the_scan_plane_and_reconstructs_its_point() -> None:
    points = work_volume(RADIUS, HEIGHT)
    index, phi, p_L = sightings(points, H)
    assert index.size > points.shape[0]  # most points are seen on both sides of the axis
    assert np.allclose(p_L[:, 2], 0.0, atol=1e-12)
    assert np.allclose(lidar_to_dynamic(p_L, phi, H), points[index], atol=1e-12)


@pytest.mark.parametrize(
    "sigma",
    [
        {"tx": 2e-5, "tz": 2e-5, "ry": math.radians(0.03), "rz": math.radians(0.005)},
        {"tx": 5e-4, "tz": 2e-5, "ry": math.radians(0.01), "rz": math.radians(0.005)},
        {"tx": 2e-5, "tz": 5e-4, "ry": math.radians(0.1), "rz": math.radians(0.05)},
    ],
    ids=["ry-limited", "tx-limited", "mixed"],
)
def test_the_95_percent_prediction_covers_95_percent_of_true_distortions(
    sigma: dict[str, float],
) -> None:
    predicted = predicted_error(H, sigma, radius=RADIUS, height=HEIGHT)
    rng = np.random.default_rng(7)
    n, covered = 400, 0
    for _ in range(n):
        wrong = H.with_(**{k: getattr(H, k) + rng.normal() * s for k, s in sigma.items()})
        covered += true_distortion(wrong, H, radius=RADIUS, height=HEIGHT)["max_m"] <= (
            predicted.max_m
        )
    # binomial 95 % over 400 draws: 380 ± 9 (2σ)
    assert 366 <= covered <= 394, covered


def test_a_rigid_motion_of_the_object_is_no_distortion() -> None:
    # an error along the axis (the gauge) only moves the whole reconstruction along it
    a = H.axis_direction()
    wrong = H.with_(tx=H.tx + 1e-3 * a[0], ty=H.ty + 1e-3 * a[1], tz=H.tz + 1e-3 * a[2])
    assert true_distortion(wrong, H, radius=RADIUS, height=HEIGHT)["max_m"] < 1e-9
    # an uncertainty only along the axis predicts no distortion either
    record = {"parameters": ["tx", "ty", "tz"], "matrix": (np.outer(a, a) * 1e-6).tolist()}
    sigma = dict.fromkeys(("tx", "ty", "tz"), 1e-3)
    predicted = predicted_error(H, sigma, record, radius=RADIUS, height=HEIGHT)
    assert predicted.max_m == pytest.approx(0.0, abs=1e-9)


def test_the_covariance_is_used_not_only_the_sigma() -> None:
    sigma = {"tx": 1e-4, "tz": 1e-4, "ry": math.radians(0.05), "rz": math.radians(0.01)}
    names = ["tx", "tz", "ry", "rz"]
    s = np.array([sigma[n] for n in names])
    independent = predicted_error(H, sigma, radius=RADIUS, height=HEIGHT)
    # tz and ry strongly correlated (the spin target fixes tz + ry·h): a different prediction
    corr = np.eye(4)
    corr[1, 2] = corr[2, 1] = -0.95
    record = {"parameters": names, "matrix": (np.outer(s, s) * corr).tolist()}
    correlated = predicted_error(H, sigma, record, radius=RADIUS, height=HEIGHT)
    assert abs(correlated.max_m - independent.max_m) > 0.05 * independent.max_m


def test_a_bias_bound_adds_its_worst_case() -> None:
    sigma = {"tx": 1e-5, "tz": 1e-5, "ry": math.radians(0.001), "rz": math.radians(0.001)}
    plain = predicted_error(H, sigma, radius=RADIUS, height=HEIGHT)
    biased = predicted_error(
        H, sigma, radius=RADIUS, height=HEIGHT, bias={"ry": math.radians(0.05)}
    )
    wrong = H.with_(ry=H.ry + math.radians(0.05))
    actual = true_distortion(wrong, H, radius=RADIUS, height=HEIGHT)["max_m"]
    assert biased.bias_m == pytest.approx(actual, rel=0.05)
    assert biased.max_m == pytest.approx(plain.max_m + biased.bias_m)


def test_the_worst_place_is_reported_inside_the_volume() -> None:
    sigma = {"tx": 1e-5, "tz": 1e-5, "ry": math.radians(0.05), "rz": math.radians(0.001)}
    p = predicted_error(H, sigma, radius=RADIUS, height=HEIGHT)
    x, y, z = p.as_dict()["worst_point_m"]
    # an ry error grows with the height: the worst point is on the top of the volume
    assert x == pytest.approx(HEIGHT) and math.hypot(y, z) <= RADIUS + 1e-9
    assert p.per_point_m.shape[0] == p.points.shape[0]
