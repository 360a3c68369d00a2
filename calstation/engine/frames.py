"""Frames and parameters (DESIGN §2). Every convention here is fixed: independent tools check it.

- Lidar frame L: the scan plane is z_L = 0; a return (ρ, α) is ``p_L = (ρ·sin α, ρ·cos α, 0)``.
- Static platform frame P: origin at the centre of the platter's top surface; +X_P is the rotation
  axis, pointing up out of the platter.
- Dynamic frame D: fixed to the platter; ``p_P = Rx(φ)·p_D`` with φ the platter angle.
- Extrinsics H = (tx, ty, tz, rx, ry, rz): the pose of P in L, ``p_L = R·p_P + t`` with
  ``R = Rz(rz)·Ry(ry)·Rx(rx)`` (scipy ``Rotation.from_euler("xyz", [rx, ry, rz])``).

All functions are pure, work on arrays, and use metres and radians.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import SupportsFloat

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calstation.errors import FrameError

FloatArray = NDArray[np.float64]

PARAMETER_NAMES: tuple[str, ...] = ("tx", "ty", "tz", "rx", "ry", "rz")
FREE_PARAMETER_NAMES: tuple[str, ...] = ("tx", "ty", "tz", "ry", "rz")
"""rx is a free gauge (it only shifts the encoder zero) and is held at 0."""


def rot_x(angle: float | FloatArray) -> FloatArray:
    """Rotation matrix about +X by ``angle`` (rad): shape (3, 3), or (N, 3, 3) for an array."""
    a = np.asarray(angle, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    one, zero = np.ones_like(a), np.zeros_like(a)
    m = np.stack(
        [
            np.stack([one, zero, zero], axis=-1),
            np.stack([zero, c, -s], axis=-1),
            np.stack([zero, s, c], axis=-1),
        ],
        axis=-2,
    )
    return m


def rot_y(angle: float) -> FloatArray:
    """Rotation matrix about +Y by ``angle`` (rad), shape (3, 3)."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(angle: float) -> FloatArray:
    """Rotation matrix about +Z by ``angle`` (rad), shape (3, 3)."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def euler_to_matrix(rx: float, ry: float, rz: float) -> FloatArray:
    """``R = Rz(rz)·Ry(ry)·Rx(rx)``, shape (3, 3)."""
    return rot_z(rz) @ rot_y(ry) @ rot_x(rx)


def rowdot(a: FloatArray, b: FloatArray) -> FloatArray:
    """(N,) the dot product of each row of ``a`` with the same row of ``b`` ((N, 3) each)."""
    out: FloatArray = np.einsum("ij,ij->i", a, b)
    return out


def rotation_derivative(x6: FloatArray, i: int, h: float = 1e-6) -> FloatArray:
    """∂R/∂x6[i] (i = 3, 4, 5: rx, ry, rz) of :func:`euler_to_matrix` at the (6,) vector
    ``x6`` (tx … rz), by a central difference (exact to about 1e-10)."""
    up, down = np.array(x6, dtype=np.float64), np.array(x6, dtype=np.float64)
    up[i] += h
    down[i] -= h
    out: FloatArray = (euler_to_matrix(*(float(a) for a in up[3:6]))
                       - euler_to_matrix(*(float(a) for a in down[3:6]))) / (2 * h)
    return out


def matrix_to_euler(R: ArrayLike) -> tuple[float, float, float]:
    """Inverse of :func:`euler_to_matrix`: (rx, ry, rz) in radians, ry in [-π/2, π/2]."""
    m = _check_rotation(R)
    from scipy.spatial.transform import Rotation  # scipy is slow to import

    rx, ry, rz = Rotation.from_matrix(m).as_euler("xyz")
    return float(rx), float(ry), float(rz)


def as_float(value: object) -> float:
    """``float(value)`` of a value read from a file or a mapping: a number or its text;
    TypeError (as ``float`` raises it) for anything else, ValueError for text that is no
    number."""
    if isinstance(value, str | SupportsFloat):
        return float(value)
    raise TypeError(
        f"float() argument must be a string or a real number, not '{type(value).__name__}'"
    )


@dataclass(frozen=True)
class Extrinsics:
    """The calibration H: pose of the platform frame P in the lidar frame L.

    Translations in metres, rotations in radians. ``p_L = R·p_P + t``.
    """

    tx: float = 0.0
    ty: float = 0.0
    tz: float = 0.0
    rx: float = 0.0
    ry: float = 0.0
    rz: float = 0.0

    def __post_init__(self) -> None:
        for name in PARAMETER_NAMES:
            value = getattr(self, name)
            if not math.isfinite(value):
                raise FrameError(f"extrinsics parameter {name} is not finite: {value!r}")

    # --- conversions -------------------------------------------------------------------------
    @property
    def R(self) -> FloatArray:
        """Rotation from P to L, (3, 3)."""
        return euler_to_matrix(self.rx, self.ry, self.rz)

    @property
    def t(self) -> FloatArray:
        """Translation of P's origin in L, (3,) metres."""
        return np.array([self.tx, self.ty, self.tz])

    def as_vector(self) -> FloatArray:
        """(tx, ty, tz, rx, ry, rz) as a (6,) array."""
        return np.array([getattr(self, n) for n in PARAMETER_NAMES], dtype=np.float64)

    @classmethod
    def from_vector(cls, v: ArrayLike) -> Extrinsics:
        """Build from (tx, ty, tz, rx, ry, rz)."""
        arr = np.asarray(v, dtype=np.float64).reshape(-1)
        if arr.shape != (6,):
            raise FrameError(f"extrinsics vector must have 6 values, got {arr.shape[0]}")
        return cls(*(float(x) for x in arr))

    def as_matrix(self) -> FloatArray:
        """The 4×4 homogeneous transform T_L_P (maps homogeneous P points to L)."""
        T = np.eye(4)
        T[:3, :3] = self.R
        T[:3, 3] = self.t
        return T

    @classmethod
    def from_matrix(cls, T: ArrayLike) -> Extrinsics:
        """Build from a 4×4 homogeneous transform T_L_P."""
        m = np.asarray(T, dtype=np.float64)
        if m.shape != (4, 4):
            raise FrameError(f"T_L_P must be 4×4, got shape {m.shape}")
        if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
            raise FrameError(f"T_L_P last row must be [0, 0, 0, 1], got {m[3].tolist()}")
        rx, ry, rz = matrix_to_euler(m[:3, :3])
        return cls(float(m[0, 3]), float(m[1, 3]), float(m[2, 3]), rx, ry, rz)

    def as_quaternion(self) -> FloatArray:
        """Rotation as a unit quaternion (x, y, z, w), scalar last (scipy/ROS order), w ≥ 0."""
        from scipy.spatial.transform import Rotation  # scipy is slow to import

        q = Rotation.from_matrix(self.R).as_quat()
        return np.asarray(q if q[3] >= 0 else -q, dtype=np.float64)

    @classmethod
    def from_quaternion(cls, translation: ArrayLike, quaternion_xyzw: ArrayLike) -> Extrinsics:
        """Build from a translation (3,) in metres and a quaternion (x, y, z, w)."""
        q = np.asarray(quaternion_xyzw, dtype=np.float64)
        if q.shape != (4,) or not np.isfinite(q).all() or np.linalg.norm(q) < 1e-12:
            raise FrameError(f"quaternion must be 4 finite values, not all zero: {q.tolist()}")
        from scipy.spatial.transform import Rotation  # scipy is slow to import

        rx, ry, rz = Rotation.from_quat(q / np.linalg.norm(q)).as_euler("xyz")
        tr = np.asarray(translation, dtype=np.float64).reshape(3)
        return cls(float(tr[0]), float(tr[1]), float(tr[2]), float(rx), float(ry), float(rz))

    def as_dict(self) -> dict[str, float]:
        """{"tx": …, "rz": …} in metres and radians."""
        return {n: float(getattr(self, n)) for n in PARAMETER_NAMES}

    @classmethod
    def from_dict(cls, d: Mapping[str, object]) -> Extrinsics:
        """Build from a mapping with keys tx, ty, tz, rx, ry, rz (rx defaults to 0)."""
        missing = [n for n in PARAMETER_NAMES if n not in d and n != "rx"]
        if missing:
            raise FrameError(f"extrinsics is missing {', '.join(missing)}")
        try:
            return cls(**{n: as_float(d.get(n, 0.0)) for n in PARAMETER_NAMES})
        except (TypeError, ValueError) as exc:
            raise FrameError(f"extrinsics values must be numbers: {exc}") from exc

    def with_(self, **changes: float) -> Extrinsics:
        """A copy with some parameters replaced."""
        return replace(self, **changes)

    def axis_direction(self) -> FloatArray:
        """The rotation axis +X_P expressed in L, a unit (3,) vector."""
        return self.R[:, 0].copy()

    def urdf_origin(self) -> str:
        """A URDF ``<origin>`` element of P in L (``rpy`` = fixed-axis roll, pitch, yaw)."""
        return (
            f'<origin xyz="{self.tx:.9g} {self.ty:.9g} {self.tz:.9g}" '
            f'rpy="{self.rx:.9g} {self.ry:.9g} {self.rz:.9g}"/>'
        )


def _check_rotation(R: ArrayLike) -> FloatArray:
    m = np.asarray(R, dtype=np.float64)
    if m.shape != (3, 3):
        raise FrameError(f"rotation matrix must be 3×3, got shape {m.shape}")
    if not np.allclose(m @ m.T, np.eye(3), atol=1e-6) or np.linalg.det(m) < 0:
        raise FrameError("matrix is not a proper rotation (orthonormal, det +1)")
    return m


def _points(p: ArrayLike, what: str) -> FloatArray:
    arr = np.asarray(p, dtype=np.float64)
    if arr.ndim == 1 and arr.shape[0] == 3:
        arr = arr.reshape(1, 3)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise FrameError(f"{what} must have shape (N, 3), got {arr.shape}")
    return arr


# --- lidar returns -----------------------------------------------------------------------
def polar_to_lidar(range_m: ArrayLike, azimuth_rad: ArrayLike) -> FloatArray:
    """(ρ, α) → (N, 3) points in frame L: ``(ρ·sin α, ρ·cos α, 0)``.

    α = 0 is the +Y_L boresight; positive α turns toward +X_L.
    """
    rho = np.asarray(range_m, dtype=np.float64).reshape(-1)
    alpha = np.asarray(azimuth_rad, dtype=np.float64).reshape(-1)
    if rho.shape != alpha.shape:
        raise FrameError(f"range and azimuth differ in length: {rho.shape[0]} vs {alpha.shape[0]}")
    return np.column_stack([rho * np.sin(alpha), rho * np.cos(alpha), np.zeros_like(rho)])


def lidar_to_polar(p_L: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Inverse of :func:`polar_to_lidar` for points in the scan plane: (range m, azimuth rad)."""
    p = _points(p_L, "p_L")
    return np.hypot(p[:, 0], p[:, 1]), np.arctan2(p[:, 0], p[:, 1])


# --- L ↔ P ↔ D -----------------------------------------------------------------------------
def platform_to_lidar(p_P: ArrayLike, H: Extrinsics) -> FloatArray:
    """(N, 3) points in P → L: ``R·p_P + t``."""
    return _points(p_P, "p_P") @ H.R.T + H.t


def lidar_to_platform(p_L: ArrayLike, H: Extrinsics) -> FloatArray:
    """(N, 3) points in L → P: ``Rᵀ·(p_L − t)``."""
    return (_points(p_L, "p_L") - H.t) @ H.R


def dynamic_to_platform(p_D: ArrayLike, phi: ArrayLike) -> FloatArray:
    """(N, 3) points in D at platter angles φ (scalar or (N,)) → P: ``Rx(φ)·p_D``."""
    p = _points(p_D, "p_D")
    c, s = _cos_sin(phi, p.shape[0])
    y = c * p[:, 1] - s * p[:, 2]
    z = s * p[:, 1] + c * p[:, 2]
    return np.column_stack([p[:, 0], y, z])


def platform_to_dynamic(p_P: ArrayLike, phi: ArrayLike) -> FloatArray:
    """(N, 3) points in P at platter angles φ (scalar or (N,)) → D: ``Rx(φ)ᵀ·p_P``."""
    p = _points(p_P, "p_P")
    c, s = _cos_sin(phi, p.shape[0])
    y = c * p[:, 1] + s * p[:, 2]
    z = -s * p[:, 1] + c * p[:, 2]
    return np.column_stack([p[:, 0], y, z])


def lidar_to_dynamic(p_L: ArrayLike, phi: ArrayLike, H: Extrinsics) -> FloatArray:
    """Reconstruction: ``p_D = Rx(φ)ᵀ·Rᵀ·(p_L − t)``, (N, 3) metres."""
    return platform_to_dynamic(lidar_to_platform(p_L, H), phi)


def dynamic_to_lidar(p_D: ArrayLike, phi: ArrayLike, H: Extrinsics) -> FloatArray:
    """Inverse of :func:`lidar_to_dynamic`."""
    return platform_to_lidar(dynamic_to_platform(p_D, phi), H)


def _cos_sin(phi: ArrayLike, n: int) -> tuple[FloatArray, FloatArray]:
    a = np.asarray(phi, dtype=np.float64)
    if a.ndim == 0:
        a = np.full(n, float(a))
    a = a.reshape(-1)
    if a.shape[0] != n:
        raise FrameError(f"need one platter angle per point: {a.shape[0]} angles, {n} points")
    return np.cos(a), np.sin(a)


# --- encoder -------------------------------------------------------------------------------
def counts_per_revolution(ppr: int) -> int:
    """A quadrature encoder with ``ppr`` pulses per revolution gives 4·ppr counts."""
    if ppr <= 0:
        raise FrameError(f"encoder ppr must be positive, got {ppr}")
    return 4 * ppr


def counts_to_angle(count: ArrayLike, counts_per_rev: int, direction: int = 1) -> FloatArray:
    """Encoder counts → platter angle φ (rad): ``direction · 2π · count / counts_per_rev``."""
    _check_direction(direction)
    if counts_per_rev <= 0:
        raise FrameError(f"counts per revolution must be positive, got {counts_per_rev}")
    return direction * 2.0 * np.pi * np.asarray(count, dtype=np.float64) / counts_per_rev


def angle_to_counts(phi: ArrayLike, counts_per_rev: int, direction: int = 1) -> FloatArray:
    """Inverse of :func:`counts_to_angle` (fractional counts; round for a real encoder)."""
    _check_direction(direction)
    if counts_per_rev <= 0:
        raise FrameError(f"counts per revolution must be positive, got {counts_per_rev}")
    return direction * np.asarray(phi, dtype=np.float64) * counts_per_rev / (2.0 * np.pi)


def _check_direction(direction: int) -> None:
    if direction not in (1, -1):
        raise FrameError(f"encoder direction must be +1 or -1, got {direction}")


def wrap_angle(phi: ArrayLike) -> FloatArray:
    """Angles wrapped into [0, 2π)."""
    return np.mod(np.asarray(phi, dtype=np.float64), 2.0 * np.pi)
