"""The known-size cube fit: the shape strategy's last stage (calstation; docs/algorithms.md).

The box cost (:mod:`calstation.engine.shapecost`) leaves the cube's size free and reads the
axis from how much the faces blur. That blur is second order in an axis offset δ, and the box's
median faces and hull footprint make the cost jumpy, so its axis offset stayed at 0.5–0.7 mm at
1 mm of range noise however many turns were scanned. The cube's *size* is first order in δ: a
side face is seen over half a turn, and an axis offset moves its two opposite copies apart or
together by (4/π)·δ along one direction, and the other pair by the same along the other. A
rigid upright cube of the recipe's edge, fitted to every labelled return together with H, turns
that into an axis known to a few hundredths of a millimetre at 1 mm of noise.

Each return's residual is its range error against its face of that cube: the distance to the
face along its own ray (the range noise lies along the ray, so a perpendicular distance would
carry a share of it that depends on the ray's angle with the face, which H turns). The cube
stands on the platter (side faces parallel to X_D, the top perpendicular to it); its centre,
yaw and top height are free alongside tx, tz, ry and rz (ty is the gauge). The faces are
labelled under the start H, away from edges and the bottom cut, and labelled again under the
result (:data:`LABEL_ROUNDS`).

σ is the cluster-robust sandwich over 2 cm blocks (as the periodicity cost's) times
:data:`SIGMA_SCALE`, with the periodicity's model floor, and in quadrature a bias bound that
more data does not remove (``diagnostics.bias_bound``, which the accuracy budget adds at its
worst): in ry the cube twist's noise bias (the same range-error residuals on the same faces
leave the same bias), and in every parameter what the cube's edge tolerance
(``qa_cube.edge_tolerance``) moves H by: the fit leans on the edge, and a cube 0.05 mm larger
than the recipe says reads as an axis about 0.04 mm off.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from calstation.engine.cube import CubeCloud, cube_cloud
from calstation.engine.frames import PARAMETER_NAMES, Extrinsics, FloatArray, lidar_to_dynamic
from calstation.engine.geometry import face_labels, upright_box
from calstation.engine.periodicity.covariance import (
    block_ids,
    covariance_record,
    model_floor,
    parameter_covariance,
    sigma_from_covariance,
)
from calstation.engine.settings import CubeGeometry
from calstation.engine.spinscan import SpinScan
from calstation.engine.twist import away_from_grazing, face_range_noise, range_twist_bias
from calstation.errors import FineTuningError

FIT_POINTS = 200_000
"""Labelled returns the fit uses at most (a fixed random subset): 4 turns at 1000 lines/s."""
LABEL_ROUNDS = 2
"""Fits, each on the faces labelled under the previous one's H (the first under the start)."""
SIGMA_SCALE = 1.3
"""The sandwich σ's scale, as the periodicity cost's (docs/algorithms.md, the shape sweep)."""
SIGMA_BLOCK = 0.02
"""Side of the blocks (m) whose returns' residuals the sandwich lets co-vary."""
MIN_FACES = 3
"""Side faces and top together the fit needs: two adjacent sides fix both directions across
the axis; a third face ties the cube's centre."""
MAX_NFEV = 100
"""Evaluations per fit."""
RY = PARAMETER_NAMES.index("ry")


@dataclass(frozen=True)
class _Faces:
    """The labelled returns of one round and the cube's pose they were labelled against."""

    p_L: FloatArray
    """(N, 3) returns in L"""
    cos: FloatArray
    """(N,) cosine of each return's platter angle"""
    sin: FloatArray
    """(N,) sine of each return's platter angle"""
    rays: FloatArray
    """(N, 3) unit rays in L"""
    side: NDArray[np.bool_]
    """(N,) on a side face (else on the top)"""
    across_u: NDArray[np.bool_]
    """(N,) a side face whose normal is the box's first horizontal axis (else its second)"""
    sign: FloatArray
    """(N,) +1 on the face at the axis's positive end, −1 at its negative end"""
    pose: FloatArray
    """(4,) the box's centre (y, z in D), yaw (rad) and top height (x in D) under the start"""
    noise: float
    """range noise (m) on the faces"""
    faces: int
    """faces labelled"""


def _label(cloud: CubeCloud, H: Extrinsics) -> _Faces:
    """The returns on the cube's faces under H, labelled against its upright box; ``cloud``
    the cube's returns found under H or an H within a millimetre of it (the labels' bands are
    several millimetres wide)."""
    if cloud.pts.shape[0] < 500:
        raise FineTuningError(
            f"the known-size cube fit found {cloud.pts.shape[0]} returns of the cube"
        )
    p_D = lidar_to_dynamic(cloud.p_L, cloud.phi, H)
    p_D[:, 0] -= cloud.level
    centre, axes, extents = upright_box(p_D[cloud.idx], strays=True)
    labels = face_labels(p_D, centre, axes, extents)
    found = [f for f in np.unique(labels) if f >= 1 and np.count_nonzero(labels == f) >= 30]
    if len(found) < MIN_FACES:
        raise FineTuningError(
            f"the known-size cube fit needs {MIN_FACES} faces of the cube with 30 returns, "
            f"found {len(found)}"
        )
    keep = np.flatnonzero(np.isin(labels, found))
    if keep.size > FIT_POINTS:
        keep = np.sort(np.random.default_rng(0).choice(keep, FIT_POINTS, replace=False))
    p_L, phi, lab = cloud.p_L[keep], cloud.phi[keep], labels[keep]
    noise = face_range_noise(
        [p_L[lab == f] for f in found], [phi[lab == f] for f in found], H
    )
    if not math.isfinite(noise):
        raise FineTuningError("the known-size cube fit could not measure the range noise")
    yaw = math.atan2(axes[2, 1], axes[1, 1])
    top = centre[0] + 0.5 * extents[0] + cloud.level
    return _Faces(
        p_L=p_L,
        cos=np.cos(phi),
        sin=np.sin(phi),
        rays=p_L / np.linalg.norm(p_L, axis=1, keepdims=True),
        side=lab >= 2,
        across_u=lab < 4,
        sign=np.where(lab % 2 == 1, 1.0, -1.0),
        pose=np.array([centre[1], centre[2], yaw, top]),
        noise=noise,
        faces=len(found),
    )


class _RangeErrors:
    """Range errors of the labelled returns against an upright cube of edge ``edge``, as a
    function of x = (H's free parameters, centre y, centre z, yaw, top height)."""

    def __init__(self, faces: _Faces, base: FloatArray, free: list[int], edge: float) -> None:
        self.f, self.base, self.free, self.edge = faces, base, free, edge

    def H(self, x: FloatArray) -> Extrinsics:
        v = self.base.copy()
        v[self.free] = x[: len(self.free)]
        return Extrinsics.from_vector(v)

    def _to_D(self, v: FloatArray, H: Extrinsics) -> FloatArray:
        q = v @ H.R
        c, s = self.f.cos, self.f.sin
        return np.column_stack([q[:, 0], c * q[:, 1] + s * q[:, 2], -s * q[:, 1] + c * q[:, 2]])

    def __call__(self, x: FloatArray, edge: float | None = None) -> FloatArray:
        f = self.f
        H = self.H(x)
        q = self._to_D(f.p_L - H.t, H)
        r = self._to_D(f.rays, H)
        cy, cz, yaw, top = x[len(self.free):]
        c, s = math.cos(yaw), math.sin(yaw)
        ny = np.where(f.across_u, c, -s) * f.sign
        nz = np.where(f.across_u, s, c) * f.sign
        half = 0.5 * (self.edge if edge is None else edge)
        dist = np.where(f.side, ny * (q[:, 1] - cy) + nz * (q[:, 2] - cz) - half, q[:, 0] - top)
        cosine = np.where(f.side, ny * r[:, 1] + nz * r[:, 2], r[:, 0])
        out: FloatArray = dist / away_from_grazing(cosine)
        return out


@dataclass(frozen=True)
class KnownSizeFit:
    """The known-size cube fit's estimate."""

    H: Extrinsics
    sigma: dict[str, float]
    """1σ per parameter (NaN for those held: rx, ty, and ry when it is not estimated)"""
    covariance: dict[str, Any] | None
    """the covariance record of the free parameters (:func:`covariance_record`): the part of
    the uncertainty that falls with more data"""
    bias: dict[str, float]
    """per free parameter, a bound on what more data does not remove (m, rad): ``sigma`` holds
    it in quadrature, the accuracy budget adds it at its worst"""
    details: dict[str, Any]


def known_size_fit(
    scan: SpinScan,
    start: Extrinsics,
    cube: CubeGeometry,
    *,
    platter_radius: float,
    estimate_ry: bool = True,
) -> KnownSizeFit:
    """Fit H's tx, tz, rz (and ry) with an upright cube of the recipe's edge to the cube scan's
    returns, from ``start`` (within a few millimetres: the box cost's result). Raises
    :class:`FineTuningError` when the cube's faces cannot be labelled."""
    names = ("tx", "tz", "ry", "rz") if estimate_ry else ("tx", "tz", "rz")
    free = [PARAMETER_NAMES.index(n) for n in names]
    H = start.with_(rx=0.0)
    # the cube's returns are found once: the rounds move H by less than a millimetre
    cloud = cube_cloud(scan.p_L, scan.phi, H, cube.edge, platter_radius, scan.memo)
    res: Any = None
    for _ in range(LABEL_ROUNDS):
        faces = _label(cloud, H)
        base = H.as_vector()
        errors = _RangeErrors(faces, base, free, cube.edge)
        x0 = np.concatenate([base[free], faces.pose])
        res = least_squares(
            errors, x0, method="trf", loss="soft_l1", f_scale=max(0.002, 3.0 * faces.noise),
            diff_step=1e-4, x_scale=np.full(x0.size, 1e-3), max_nfev=MAX_NFEV,
        )
        H = errors.H(res.x)
    cov = _covariance(res, errors, faces, free)
    bias = _bias_bound(res, errors, faces, free, cube.edge_tolerance)
    random = sigma_from_covariance(cov, free)
    sigma = {n: math.hypot(v, bias.get(n, 0.0)) if math.isfinite(v) else v
             for n, v in random.items()}
    return KnownSizeFit(
        H=H,
        sigma=sigma,
        covariance=covariance_record(cov, free),
        bias=bias,
        details={
            "used": True,
            "faces": faces.faces,
            "returns": int(faces.p_L.shape[0]),
            "range_noise_m": faces.noise,
            "edge_m": cube.edge,
            "edge_tolerance_m": cube.edge_tolerance,
            "rms_range_error_m": float(np.sqrt(np.mean(res.fun**2))),
            "evaluations": int(res.nfev),
            "status": str(res.message),
        },
    )


def _covariance(
    res: Any, errors: _RangeErrors, faces: _Faces, free: list[int]
) -> FloatArray | None:
    """(n, n) covariance of the free parameters of H, the part that falls with more data: the
    block sandwich × :data:`SIGMA_SCALE` and the model floor."""
    H = errors.H(res.x)
    p_D = lidar_to_dynamic(faces.p_L, np.arctan2(faces.sin, faces.cos), H)
    full = parameter_covariance(res, list(range(res.x.size)), blocks=block_ids(p_D, SIGMA_BLOCK))
    if full is None:
        return None
    n = len(free)
    out: FloatArray = full[:n, :n] * SIGMA_SCALE**2 + model_floor(free)
    return out


def _bias_bound(
    res: Any, errors: _RangeErrors, faces: _Faces, free: list[int], tolerance: float
) -> dict[str, float]:
    """Per parameter, a bound on what more data does not remove (m, rad): the edge tolerance
    moved through the fit (|dx| with dx = −J⁺·∂r/∂edge·tolerance) and, in ry, the range
    errors' noise bias on the faces (the twist's: +0.08–0.10° at 2 mm)."""
    n = len(free)
    out = {PARAMETER_NAMES[i]: 0.0 for i in free}
    if tolerance > 0:
        step = 1e-5
        dr = (errors(res.x, errors.edge + step) - errors(res.x)) / step
        dx = -np.linalg.lstsq(np.asarray(res.jac), dr, rcond=None)[0][:n]
        out.update({PARAMETER_NAMES[i]: abs(float(dx[k])) * tolerance
                    for k, i in enumerate(free)})
    if RY in free:
        out["ry"] += range_twist_bias(faces.noise)
    return out
