"""Round trips and conventions of calstation.engine.frames (DESIGN §2)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from calstation.engine import frames
from calstation.engine.frames import Extrinsics
from calstation.errors import FrameError

finite = st.floats(-5.0, 5.0, allow_nan=False, allow_infinity=False)
angle = st.floats(-math.pi + 1e-3, math.pi - 1e-3)
half_angle = st.floats(-math.pi / 2 + 1e-3, math.pi / 2 - 1e-3)
extrinsics = st.builds(Extrinsics, finite, finite, finite, angle, half_angle, angle)
points = arrays(np.float64, st.tuples(st.integers(1, 20), st.just(3)), elements=finite)


def test_rotation_order_matches_scipy_xyz() -> None:
    H = Extrinsics(0, 0, 0, 0.1, -0.2, 0.3)
    expected = Rotation.from_euler("xyz", [0.1, -0.2, 0.3]).as_matrix()
    assert np.allclose(H.R, expected)
    assert np.allclose(H.R, frames.rot_z(0.3) @ frames.rot_y(-0.2) @ frames.rot_x(0.1))


def test_polar_convention() -> None:
    # α = 0 is +Y_L; positive α turns toward +X_L.
    p = frames.polar_to_lidar([2.0, 1.0], [0.0, math.pi / 2])
    assert np.allclose(p, [[0.0, 2.0, 0.0], [1.0, 0.0, 0.0]])


def test_design_example_pose() -> None:
    # Lidar 1 m from the platter centre, looking down at 45°: the axis +X_P points up, away from
    # the lidar's side, and the lidar sits above the platter on the −Y_P side.
    H = Extrinsics(0.0, 1.0, 0.0, 0.0, 0.0, math.radians(-45))
    lidar_in_P = frames.lidar_to_platform([0.0, 0.0, 0.0], H)[0]
    assert lidar_in_P[0] == pytest.approx(math.sqrt(0.5))
    assert lidar_in_P[1] == pytest.approx(-math.sqrt(0.5))
    assert lidar_in_P[2] == pytest.approx(0.0)


@given(extrinsics)
def test_matrix_round_trip(H: Extrinsics) -> None:
    back = Extrinsics.from_matrix(H.as_matrix())
    assert np.allclose(back.as_matrix(), H.as_matrix(), atol=1e-9)
    assert np.allclose(back.as_vector(), H.as_vector(), atol=1e-7)


@given(extrinsics)
def test_quaternion_round_trip(H: Extrinsics) -> None:
    q = H.as_quaternion()
    assert np.isclose(np.linalg.norm(q), 1.0)
    back = Extrinsics.from_quaternion(H.t, q)
    assert np.allclose(back.as_vector(), H.as_vector(), atol=1e-7)


@given(extrinsics)
def test_vector_and_dict_round_trip(H: Extrinsics) -> None:
    assert Extrinsics.from_vector(H.as_vector()) == H
    assert Extrinsics.from_dict(H.as_dict()) == H


@given(extrinsics, points)
def test_lidar_platform_round_trip(H: Extrinsics, p: np.ndarray) -> None:
    p_L = frames.platform_to_lidar(p, H)
    assert np.allclose(frames.lidar_to_platform(p_L, H), p, atol=1e-9)
    # and it is the rigid transform p_L = R·p_P + t
    assert np.allclose(p_L, (H.as_matrix() @ np.c_[p, np.ones(len(p))].T).T[:, :3])


@given(points, st.floats(-20.0, 20.0))
def test_platform_dynamic_round_trip(p: np.ndarray, phi: float) -> None:
    p_P = frames.dynamic_to_platform(p, phi)
    assert np.allclose(p_P, p @ frames.rot_x(phi).T)
    assert np.allclose(frames.platform_to_dynamic(p_P, phi), p, atol=1e-9)


@given(extrinsics, points, st.floats(-20.0, 20.0))
def test_lidar_dynamic_round_trip(H: Extrinsics, p: np.ndarray, phi: float) -> None:
    phis = np.full(len(p), phi)
    p_L = frames.dynamic_to_lidar(p, phis, H)
    expected = frames.rot_x(phi).T @ H.R.T @ (p_L - H.t).T
    assert np.allclose(frames.lidar_to_dynamic(p_L, phis, H), expected.T, atol=1e-9)
    assert np.allclose(frames.lidar_to_dynamic(p_L, phis, H), p, atol=1e-8)


@given(
    arrays(np.float64, st.integers(1, 50), elements=st.floats(0.01, 100.0)),
    st.floats(-math.pi + 1e-6, math.pi - 1e-6),
)
def test_polar_round_trip(rho: np.ndarray, alpha: float) -> None:
    alphas = np.full(len(rho), alpha)
    r, a = frames.lidar_to_polar(frames.polar_to_lidar(rho, alphas))
    assert np.allclose(r, rho)
    assert np.allclose(a, alphas)


@settings(max_examples=50)
@given(
    st.integers(-10**7, 10**7),
    st.integers(1, 100_000),
    st.sampled_from([1, -1]),
)
def test_encoder_round_trip(count: int, ppr: int, direction: int) -> None:
    cpr = frames.counts_per_revolution(ppr)
    phi = frames.counts_to_angle(count, cpr, direction)
    assert np.isclose(frames.angle_to_counts(phi, cpr, direction), count)
    assert np.isclose(frames.counts_to_angle(cpr, cpr, direction), direction * 2 * math.pi)


def test_bad_inputs_raise_frame_errors() -> None:
    with pytest.raises(FrameError, match="direction"):
        frames.counts_to_angle(1, 4096, 0)
    with pytest.raises(FrameError, match="ppr"):
        frames.counts_per_revolution(0)
    with pytest.raises(FrameError, match="not finite"):
        Extrinsics(tx=float("nan"))
    with pytest.raises(FrameError, match="4×4"):
        Extrinsics.from_matrix(np.eye(3))
    with pytest.raises(FrameError, match=r"\(N, 3\)"):
        frames.lidar_to_platform(np.zeros((4, 2)), Extrinsics())
    with pytest.raises(FrameError, match="one platter angle per point"):
        frames.platform_to_dynamic(np.zeros((4, 3)), np.zeros(3))


def test_urdf_origin_snippet() -> None:
    H = Extrinsics(0.01, 1.0, -0.002, 0.0, 0.001, -0.7)
    assert H.urdf_origin() == '<origin xyz="0.01 1 -0.002" rpy="0 0.001 -0.7"/>'
