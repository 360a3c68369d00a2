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


def distortion_points(
    p_L: FloatArray,
    phi: FloatArray,
    estimate: Extrinsics,
    truth: Extrinsics,
    *,
    margin: float = 0.005,
    platter_radius: float = DEFAULT_PLATTER_RADIUS,
) -> dict[str, float]:
    """Reconstruction distortion on the object above the platter ((N, 3) returns in L, (N,) φ).

    The object is the returns more than ``margin`` above the platter (under the true H) and
    inside the platter. Returns ``rms_m``, ``max_m`` after Kabsch alignment, ``points``.
    """
    # height along the axis and distance from it need no platter angle: select in P first
    q = p_L @ truth.R
    q -= truth.t @ truth.R
    r2 = np.einsum("ij,ij->i", q[:, 1:], q[:, 1:])
    sel = np.flatnonzero((q[:, 0] > margin) & (q[:, 0] < 1.0) & (r2 < platter_radius**2))
    if sel.size < 10:
        raise CalibrationError(
            f"only {sel.size} returns above the platter: no object to measure distortion on"
        )
    est_D = lidar_to_dynamic(p_L[sel], phi[sel], estimate)
    true_D = lidar_to_dynamic(p_L[sel], phi[sel], truth)
    R, t = kabsch(est_D, true_D)
    d = np.linalg.norm(est_D @ R.T + t - true_D, axis=1)
    return {
        "rms_m": float(np.sqrt(np.mean(d**2))),
        "max_m": float(np.max(d)),
        "points": float(sel.size),
    }


def reconstruction_distortion(
    recording: Scan, estimate: Extrinsics, truth: Extrinsics, *, prepared: SpinScan | None = None
) -> dict[str, float]:
    """Distortion of a recording's object (e.g. the QA cube) reconstructed with ``estimate``
    instead of ``truth``: ``rms_m``, ``max_m`` (metres) after the best rigid alignment.
    ``prepared``: the recording's returns already prepared
    (:func:`calstation.engine.spinscan.from_recording`), else they are prepared here."""
    from calstation.engine.spinscan import from_recording

    scan = prepared if prepared is not None else from_recording(recording)
    return distortion_points(scan.p_L, scan.phi, estimate, truth)
