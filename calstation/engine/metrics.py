"""Ground-truth accuracy metrics (DESIGN §8): what the simulator knows and the paper could not.

- Axis errors: the angle between the estimated and true rotation axes, and the distance between
  the two axis lines measured in the plane through the true platter centre perpendicular to the
  true axis (independent of the gauge along the axis); per-parameter errors with the gauge
  difference along the axis reported separately.
- Reconstruction distortion: the same recording reconstructed with the estimated and with the
  true H; after the best rigid alignment (Kabsch, same points) the RMS and maximum displacement.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from calstation.engine.frames import PARAMETER_NAMES, Extrinsics, FloatArray, lidar_to_dynamic
from calstation.engine.settings import DEFAULT_PLATTER_RADIUS
from calstation.errors import CalibrationError

if TYPE_CHECKING:
    from calstation.engine.scan import Scan
    from calstation.engine.spinscan import SpinScan


def axis_errors(estimate: Extrinsics, truth: Extrinsics) -> dict[str, float]:
    """Axis and parameter errors of ``estimate`` against ``truth`` (metres, radians).

    Keys: ``axis_angle_rad``; ``axis_offset_m`` (distance between the axis lines in the plane
    through the true platter centre perpendicular to the true axis); ``along_axis_m`` (the
    gauge: how far the estimated origin sits along the true axis); ``<name>_error`` for tx … rz
    (estimate − truth; tx/ty depend on the gauge, see ``along_axis_m``).
    """
    a_e, a_t = estimate.axis_direction(), truth.axis_direction()
    cosang = abs(float(np.dot(a_e, a_t)))
    angle = math.acos(min(1.0, cosang))
    denom = float(np.dot(a_t, a_e))
    if abs(denom) < 1e-9:
        raise CalibrationError("the estimated axis is perpendicular to the true axis")
    lam = float(np.dot(a_t, truth.t - estimate.t)) / denom
    p = estimate.t + lam * a_e  # the estimated axis where it crosses the true centre's plane
    offset = float(np.linalg.norm(p - truth.t))
    out = {
        "axis_angle_rad": angle,
        "axis_offset_m": offset,
        "along_axis_m": float(np.dot(estimate.t - truth.t, a_t)),
    }
    ev, tv = estimate.as_vector(), truth.as_vector()
    for i, name in enumerate(PARAMETER_NAMES):
        out[f"{name}_error"] = float(ev[i] - tv[i])
    return out


def kabsch(source: FloatArray, target: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Best rigid transform (R (3, 3), t (3,)) with ``R·source + t ≈ target`` (least squares,
    proper rotation) for corresponding (N, 3) point sets."""
    if source.shape != target.shape or source.ndim != 2 or source.shape[1] != 3:
        raise CalibrationError(
            f"Kabsch needs two (N, 3) sets of the same shape, got {source.shape}, {target.shape}"
        )
    cs, ct = source.mean(axis=0), target.mean(axis=0)
    h = (source - cs).T @ (target - ct)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    R = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return R, ct - R @ cs


OBJECT_MARGIN = 0.005
"""The distortion's object is the returns more than this above the platter (m)."""


@dataclass(frozen=True)
class _Object:
    """A recording's object above the platter, found under the true H: its returns in L,
    their platter angles, and where the true H puts them in D."""

    p_L: FloatArray
    phi: FloatArray
    true_D: FloatArray


def _object(
    p_L: FloatArray, phi: FloatArray, truth: Extrinsics, margin: float, platter_radius: float
) -> _Object:
    """The returns more than ``margin`` above the platter and inside it, under ``truth``."""
    # height along the axis and distance from it need no platter angle: select in P first
    q = p_L @ truth.R
    q -= truth.t @ truth.R
    r2 = np.einsum("ij,ij->i", q[:, 1:], q[:, 1:])
    sel = np.flatnonzero((q[:, 0] > margin) & (q[:, 0] < 1.0) & (r2 < platter_radius**2))
    if sel.size < 10:
        raise CalibrationError(
            f"only {sel.size} returns above the platter: no object to measure distortion on"
        )
    return _Object(p_L[sel], phi[sel], lidar_to_dynamic(p_L[sel], phi[sel], truth))


def _distortion(obj: _Object, estimate: Extrinsics) -> dict[str, float]:
    est_D = lidar_to_dynamic(obj.p_L, obj.phi, estimate)
    R, t = kabsch(est_D, obj.true_D)
    d = np.linalg.norm(est_D @ R.T + t - obj.true_D, axis=1)
    return {
        "rms_m": float(np.sqrt(np.mean(d**2))),
        "max_m": float(np.max(d)),
        "points": float(obj.p_L.shape[0]),
    }


def distortion_points(
    p_L: FloatArray,
    phi: FloatArray,
    estimate: Extrinsics,
    truth: Extrinsics,
    *,
    margin: float = OBJECT_MARGIN,
    platter_radius: float = DEFAULT_PLATTER_RADIUS,
) -> dict[str, float]:
    """Reconstruction distortion on the object above the platter ((N, 3) returns in L, (N,) φ).

    The object is the returns more than ``margin`` above the platter (under the true H) and
    inside the platter. Returns ``rms_m``, ``max_m`` after Kabsch alignment, ``points``.
    """
    return _distortion(_object(p_L, phi, truth, margin, platter_radius), estimate)


def reconstruction_distortion(
    recording: Scan | None,
    estimate: Extrinsics,
    truth: Extrinsics,
    *,
    prepared: SpinScan | None = None,
) -> dict[str, float]:
    """Distortion of a recording's object (e.g. the QA cube) reconstructed with ``estimate``
    instead of ``truth``: ``rms_m``, ``max_m`` (metres) after the best rigid alignment.
    ``prepared``: the recording's returns already prepared
    (:func:`calstation.engine.spinscan.from_recording`), else they are prepared here (one of
    the two is needed); its object, found under ``truth``, is kept in its memo for the next
    estimate (the bench measures every start's estimate on one scan)."""
    from calstation.engine.spinscan import prepared_or_read

    scan = prepared_or_read(recording, prepared)
    key = f"distortion object {truth.as_vector().tobytes().hex()}"
    obj = scan.memo.get(key)
    if not isinstance(obj, _Object):
        obj = _object(scan.p_L, scan.phi, truth, OBJECT_MARGIN, DEFAULT_PLATTER_RADIUS)
        scan.memo[key] = obj
    return _distortion(obj, estimate)
