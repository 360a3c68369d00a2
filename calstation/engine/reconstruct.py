"""Reconstruction: a recording plus the calibration H → a 3D point cloud in the platter frame D.

Each point gets its own platter angle φ, interpolated from the encoder at the point's own time
(lines are not instantaneous: the platter turns during one), then
``p_D = Rx(φ)ᵀ·Rᵀ·(p_L − t)`` (DESIGN §2).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from calstation.engine.frames import Extrinsics, lidar_to_dynamic
from calstation.engine.rangemodel import IDENTITY, RangeModel
from calstation.engine.scan import Scan


def reconstruct(
    recording: Scan, H: Extrinsics, encoder_latency_s: float | None = None,
    range_model: RangeModel = IDENTITY,
) -> NDArray[np.float64]:
    """The recording's valid points in frame D: (N, 3) metres.

    Invalid returns and points outside the encoder's time span are left out (see
    :meth:`Scan.points_lidar`). ``encoder_latency_s``, when given (a calibration's
    estimated lidar–encoder time offset), replaces the recording's configured latency;
    ``range_model`` (a calibration's, DESIGN §9) corrects every range first: its offset and
    scale error (the incidence bias needs the surfaces' normals, which a plain reconstruction
    does not know).
    """
    if encoder_latency_s is not None:
        recording = recording.with_encoder_latency(encoder_latency_s)
    p_L, phi = recording.points_lidar()
    return lidar_points_to_dynamic(range_model.points(p_L), phi, H)


def lidar_points_to_dynamic(
    p_L: NDArray[np.float64], phi: NDArray[np.float64], H: Extrinsics
) -> NDArray[np.float64]:
    """``p_D = Rx(φ)ᵀ·Rᵀ·(p_L − t)`` for (N, 3) points in L and (N,) φ (rad): (N, 3) in D.

    Same as :func:`calstation.engine.frames.lidar_to_dynamic`, fused for millions of points.
    """
    p = np.asarray(p_L, dtype=np.float64)
    a = np.asarray(phi, dtype=np.float64).reshape(-1)
    if p.ndim != 2 or p.shape[1] != 3 or a.shape[0] != p.shape[0]:
        return lidar_to_dynamic(p, a, H)  # lets frames raise its shape errors
    # Rᵀ·(p_L − t) column by column: a (N,3)@(3,3) matmul is far slower on tall arrays
    R, t = H.R, H.t
    d = [p[:, i] - t[i] for i in range(3)]
    x = d[0] * R[0, 0] + d[1] * R[1, 0] + d[2] * R[2, 0]
    y = d[0] * R[0, 1] + d[1] * R[1, 1] + d[2] * R[2, 1]
    z = d[0] * R[0, 2] + d[1] * R[1, 2] + d[2] * R[2, 2]
    c, s = np.cos(a), np.sin(a)
    out = np.empty_like(p)
    out[:, 0] = x
    out[:, 1] = c * y + s * z
    out[:, 2] = c * z - s * y
    return out


def platter_cloud(
    p_L: NDArray[np.float64], phi: NDArray[np.float64], H: Extrinsics, platter_radius: float,
    height: float = 0.6, margin: float = 0.01,
) -> NDArray[np.float64]:
    """The returns (N, 3) in L at platter angles φ (N,) reconstructed in D under H, keeping
    what stands on the platter and its top: within ``platter_radius`` of the axis (plus
    ``margin``), from ``margin`` below the platter top to ``height`` above it (metres)."""
    from calstation.engine.geometry import segment_above_platter

    p_D = lidar_points_to_dynamic(p_L, phi, H)
    keep = segment_above_platter(p_D, margin=-margin, radius=platter_radius + margin,
                                 height=height)
    out: NDArray[np.float64] = p_D[keep]
    return out
