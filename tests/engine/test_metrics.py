"""Ground-truth metrics (DESIGN §8)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calstation.engine.frames import Extrinsics
from calstation.engine.metrics import axis_errors, distortion_points, kabsch

TRUTH = Extrinsics(0.002, 1.25, 0.003, 0.0, math.radians(0.1), math.radians(-45))


def test_identical_is_zero() -> None:
    e = axis_errors(TRUTH, TRUTH)
    assert e["axis_angle_rad"] == pytest.approx(0.0, abs=1e-7)
    assert e["axis_offset_m"] == pytest.approx(0.0, abs=1e-12)
    assert all(e[f"{n}_error"] == 0.0 for n in ("tx", "ty", "tz", "rx", "ry", "rz"))


def test_shift_along_the_axis_is_gauge_only() -> None:
    a = TRUTH.axis_direction()
    t = TRUTH.t + 0.05 * a
    est = TRUTH.with_(tx=t[0], ty=t[1], tz=t[2])
    e = axis_errors(est, TRUTH)
    assert e["axis_offset_m"] == pytest.approx(0.0, abs=1e-12)
    assert e["along_axis_m"] == pytest.approx(0.05)
    assert e["tx_error"] != 0.0


def test_perpendicular_shift_and_tilt() -> None:
    e = axis_errors(TRUTH.with_(tz=TRUTH.tz + 0.001), TRUTH)  # Z_L is ⟂ to the axis here
    assert e["axis_offset_m"] == pytest.approx(0.001, rel=1e-3)
    e = axis_errors(TRUTH.with_(rz=TRUTH.rz + math.radians(0.05)), TRUTH)
    assert math.degrees(e["axis_angle_rad"]) == pytest.approx(0.05, rel=1e-3)
    assert e["axis_offset_m"] == pytest.approx(0.0, abs=1e-12)  # tilt about the centre


def test_kabsch_recovers_a_rigid_motion() -> None:
    rng = np.random.default_rng(0)
    p = rng.normal(size=(50, 3))
    R = Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix()
    t = np.array([1.0, 2.0, 3.0])
    R2, t2 = kabsch(p, p @ R.T + t)
    np.testing.assert_allclose(R2, R, atol=1e-12)
    np.testing.assert_allclose(t2, t, atol=1e-12)


def test_distortion_zero_for_truth_and_positive_for_an_error() -> None:
    rng = np.random.default_rng(1)
    # returns of an object above the platter seen at many platter angles
    n = 5000
    p_D = np.column_stack(
        [rng.uniform(0.01, 0.1, n), rng.uniform(-0.05, 0.05, n), rng.uniform(-0.05, 0.05, n)]
    )
    phi = rng.uniform(0, 2 * math.pi, n)
    from calstation.engine.frames import dynamic_to_lidar

    p_L = dynamic_to_lidar(p_D, phi, TRUTH)
    d0 = distortion_points(p_L, phi, TRUTH, TRUTH)
    assert d0["rms_m"] == pytest.approx(0.0, abs=1e-12)
    d1 = distortion_points(p_L, phi, TRUTH.with_(tz=TRUTH.tz + 0.002), TRUTH)
    assert d1["rms_m"] > 5e-4 and d1["max_m"] >= d1["rms_m"]


def test_the_distortion_of_each_estimate_on_one_prepared_scan_is_its_own() -> None:
    """The object found under the truth is kept with the prepared scan: every estimate's
    distortion on it equals the distortion computed afresh, and another truth finds its own."""
    from calstation.engine.frames import dynamic_to_lidar
    from calstation.engine.metrics import reconstruction_distortion
    from calstation.engine.spinscan import prepare

    rng = np.random.default_rng(2)
    n = 4000
    p_D = np.column_stack(
        [rng.uniform(-0.02, 0.1, n), rng.uniform(-0.05, 0.05, n), rng.uniform(-0.05, 0.05, n)]
    )
    phi = rng.uniform(0, 2 * math.pi, n)
    p_L = dynamic_to_lidar(p_D, phi, TRUTH)
    scan = prepare(p_L, phi)
    other = TRUTH.with_(tx=TRUTH.tx + 0.01)
    for estimate in (TRUTH.with_(tz=TRUTH.tz + 0.002), TRUTH.with_(ry=TRUTH.ry + 0.01), TRUTH):
        for truth in (TRUTH, other):
            got = reconstruction_distortion(None, estimate, truth, prepared=scan)
            assert got == distortion_points(p_L, phi, estimate, truth)  # exactly
    assert reconstruction_distortion(None, TRUTH, other, prepared=scan)["points"] != \
        reconstruction_distortion(None, TRUTH, TRUTH, prepared=scan)["points"]
