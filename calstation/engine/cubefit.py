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
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from calstation.engine.cubecast import (
    FIT_POINTS,
    MIN_FACES,
    PLATTER_POINTS,
    _Faces,
    _kept,
    _near_platter,
    _Returns,
    fixed_keys,
    model_labels,
)
from calstation.engine.cubecloud import CubeCloud, cube_cloud, segment_cube
from calstation.engine.cuberesiduals import RangeErrors, RangeSizeErrors
from calstation.engine.frames import (
    PARAMETER_NAMES,
    Extrinsics,
    FloatArray,
    lidar_to_dynamic,
)
from calstation.engine.geometry import face_labels, upright_box, veil_mask
from calstation.engine.periodicity.covariance import (
    CovarianceRecord,
    block_ids,
    covariance_record,
    model_floor,
    parameter_covariance,
    sigma_from_covariance,
)
from calstation.engine.rangemodel import (
    ESTIMATED_NAMES,
    IDENTITY,
    OFFSET,
    SCALE,
    RangeModel,
    RangeModelName,
    correct_vector,
    estimated_indices,
    unit_rays,
)
from calstation.engine.residuals import TrendRecord, residual_trends
from calstation.engine.settings import CubeGeometry
from calstation.engine.softl1 import gauss_newton_weight, soft_l1_fit
from calstation.engine.spinscan import SpinScan
from calstation.engine.twist import (
    face_range_noise,
    range_twist_bias,
)
from calstation.errors import FineTuningError
from calstation.jsonvalue import JSONObject

if TYPE_CHECKING:
    from scipy.optimize import OptimizeResult

LABEL_ROUNDS = 2
"""Fits, each on the faces labelled under the previous one's H (the first under the start), of
the known-size fit without the range model (with it, until they settle: :data:`SETTLED_M`)."""
FIRST_ROUNDS_STRIDE = 4
"""The known-size fit with the range model labels and fits every this-many-th return in the
rounds before its last (:func:`range_size_fit`); the last round uses them all."""
SETTLED_M, SETTLED_RAD = 0.1e-3, 0.1e-3
"""The known-size fit with the range model has settled when a round on every
:data:`FIRST_ROUNDS_STRIDE`-th return, after one on the same returns, moved H's translation by
less than this (m) and its rotation by less than this (rad): its labels no longer change. Then
one round on all of them. From where the box cost left two bench starts on a 30° station
(5–9 mm and up to 1.2° off: it stopped on its evaluations, ry held at the start's), a round on a
part and one on all moved ty by 6 mm in the second and ended 4 mm off, one with σ_tx 0.05 mm
for a tx 1.1 mm off; settled after four rounds, within 0.1 mm. From a start within a few
millimetres, two or three rounds on a part."""
FIRST_CLOUD = 50_000
"""The cube's returns the range fit's first labelling finds the cube's upright box in are
looked for among at most about this many returns above the platter (whole scan lines): the
box only places the model the later rounds cast their labels against, and every return above
the platter is labelled against it."""
RANGE_ROUNDS = 10
"""At most this many rounds of the known-size fit with the range model: one that has not
settled by then raises :class:`FineTuningError` (its start was too far off)."""
SIGMA_SCALE = 1.3
"""The sandwich σ's scale, as the periodicity cost's (docs/algorithms.md, the shape sweep)."""
SIGMA_BLOCK = 0.02
"""Side of the blocks (m) whose returns' residuals the sandwich lets co-vary."""
MAX_NFEV = 100
"""Evaluations per fit."""
RY = PARAMETER_NAMES.index("ry")


def _label(cloud: CubeCloud, H: Extrinsics) -> _Faces:
    """The returns on the cube's faces under H, labelled against its upright box; ``cloud``
    the cube's returns found under H or an H within a millimetre of it (the labels' bands are
    several millimetres wide)."""
    return _label_in_box(cloud, H)[0]


def _faces_found(labels: NDArray[np.int_]) -> list[int]:
    """The face labels (1–5) held by 30 returns or more of ``labels``;
    :class:`FineTuningError` when fewer than :data:`MIN_FACES` are."""
    found = [int(f) for f in np.unique(labels) if f >= 1 and np.count_nonzero(labels == f) >= 30]
    if len(found) < MIN_FACES:
        raise FineTuningError(
            f"the known-size cube fit needs {MIN_FACES} faces of the cube with 30 returns, "
            f"found {len(found)}"
        )
    return found


def _label_in_box(cloud: CubeCloud, H: Extrinsics) -> tuple[_Faces, FloatArray]:
    """:func:`_label`, and the upright box's extents (3,: its height, then across)."""
    if cloud.pts.shape[0] < 500:
        raise FineTuningError(
            f"the known-size cube fit found {cloud.pts.shape[0]} returns of the cube"
        )
    p_D = lidar_to_dynamic(cloud.p_L, cloud.phi, H)
    p_D[:, 0] -= cloud.level
    centre, axes, extents = upright_box(p_D[cloud.idx[~cloud.veil]], strays=True)
    labels = face_labels(p_D, centre, axes, extents)
    found = _faces_found(labels)
    # the same returns' keys in every round (the cloud is found once): rounds that label nearly
    # the same returns keep nearly the same ones (cubecast._kept)
    keep = _kept(np.flatnonzero(np.isin(labels, found)), fixed_keys(cloud.p_L.shape[0]),
                 FIT_POINTS)
    keep = keep[~veil_mask(cloud.p_L, keep)]  # neighbours among the returns above the platter
    p_L, phi, lab = cloud.p_L[keep], cloud.phi[keep], labels[keep]
    # a face labelled under a start far off may lie on the veils alone: counted again
    found = _faces_found(lab)
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
    ), extents


@dataclass(frozen=True)
class KnownSizeFit:
    """The known-size cube fit's estimate."""

    H: Extrinsics
    sigma: dict[str, float]
    """1σ per parameter (NaN for those held: rx, ty, and ry when it is not estimated; the range
    terms when estimated)"""
    covariance: CovarianceRecord | None
    """the covariance record of the free parameters (:func:`covariance_record`): the part of
    the uncertainty that falls with more data"""
    bias: dict[str, float]
    """per free parameter, a bound on what more data does not remove (m, rad): ``sigma`` holds
    it in quadrature, the accuracy budget adds it at its worst"""
    details: JSONObject
    range_model: RangeModel = IDENTITY
    """the range model the fit ended on (its start when not estimated)"""
    edge_direction: dict[str, float] | None = None
    """per free parameter, how far (m, rad) a cube larger than the recipe's edge by its
    tolerance moves it, with its sign: the bias bound's part that moves every parameter at once
    (None when not computed)"""
    encoder_direction: dict[str, dict[str, float]] | None = None
    """per coefficient of the encoder's angle error (:data:`~calstation.engine.encoder.
    HARMONICS`), how far each free parameter moves per radian of it (None when not computed)"""
    residuals: dict[str, TrendRecord] = field(default_factory=dict)
    """the range fit's residuals on the faces against range, incidence angle and azimuth
    (:func:`calstation.engine.residuals.residual_trends`; empty for a fit without the range
    model)"""

    def total_covariance(self) -> CovarianceRecord | None:
        """The covariance record with the bias bound's parts as the covariance they are: the
        edge tolerance's rank-one term (fully correlated across the parameters) and the
        faces' noise bias in ry. What combining this fit with another estimate weighs it by."""
        if self.covariance is None:
            return None
        names = list(self.covariance["parameters"])
        C = np.asarray(self.covariance["matrix"], dtype=np.float64).copy()
        if self.edge_direction is not None:
            v = np.array([self.edge_direction.get(n, 0.0) for n in names])
            C += np.outer(v, v)
        if "ry" in names:
            k = names.index("ry")
            edge_part = abs((self.edge_direction or {}).get("ry", 0.0))
            C[k, k] += max(self.bias.get("ry", 0.0) - edge_part, 0.0) ** 2
        return {"parameters": names, "matrix": C.tolist()}


def known_size_fit(
    scan: SpinScan,
    start: Extrinsics,
    cube: CubeGeometry,
    *,
    platter_radius: float,
    estimate_ry: bool = True,
    range_model: RangeModelName = "none",
    start_range: RangeModel = IDENTITY,
    incidence: bool = False,
    encoder: bool = False,
    gate: float | None = None,
) -> KnownSizeFit:
    """Fit H's tx, tz, rz (and ry) with an upright cube of the recipe's edge to the cube scan's
    returns, from ``start`` (within a few millimetres: the box cost's result). Raises
    :class:`FineTuningError` when the cube's faces cannot be labelled.

    ``range_model`` other than ``none``: the lidar's range terms are fitted too (and the
    incidence bias with ``incidence``), from ``start_range`` (:func:`range_size_fit`; with
    ``encoder``, how it follows the encoder's angle error too; ``gate``, see there)."""
    if range_model != "none":
        return range_size_fit(scan, start, cube, platter_radius=platter_radius,
                              estimate_ry=estimate_ry, range_model=range_model,
                              start_range=start_range, incidence=incidence, encoder=encoder,
                              gate=gate)
    names = ("tx", "tz", "ry", "rz") if estimate_ry else ("tx", "tz", "rz")
    free = [PARAMETER_NAMES.index(n) for n in names]
    H = start.with_(rx=0.0)
    # the cube's returns are found once: the rounds move H by less than a millimetre
    cloud = cube_cloud(scan.p_L, scan.phi, H, cube.edge, platter_radius, scan.memo)
    res: OptimizeResult = None
    for _ in range(LABEL_ROUNDS):
        faces = _label(cloud, H)
        base = H.as_vector()
        errors = RangeErrors(faces, base, free, cube.edge)
        x0 = np.concatenate([base[free], faces.pose])
        res = least_squares(
            errors, x0, method="trf", loss="soft_l1", f_scale=_f_scale(faces.noise),
            diff_step=1e-4, x_scale=np.full(x0.size, 1e-3), max_nfev=MAX_NFEV,
        )
        H = errors.H(res.x)
    cov = _covariance(res, errors, faces, free)
    bias = _bias_bound(res, errors, faces, free, cube.edge_tolerance)
    return KnownSizeFit(
        H=H,
        sigma=_sigma_with_bias(cov, free, bias),
        covariance=covariance_record(cov, free),
        bias=bias,
        details=_details(res, faces, cube),
    )


def _sigma_with_bias(
    cov: FloatArray | None, free: list[int], bias: dict[str, float]
) -> dict[str, float]:
    """1σ per parameter: the covariance's and the bias bound's in quadrature."""
    random = sigma_from_covariance(cov, free)
    return {n: math.hypot(v, bias.get(n, 0.0)) if math.isfinite(v) else v
            for n, v in random.items()}


def _details(res: OptimizeResult, faces: _Faces, cube: CubeGeometry) -> JSONObject:
    """What a known-size fit reports of itself (``KnownSizeFit.details``)."""
    return {
        "used": True,
        "faces": faces.faces,
        "returns": int(faces.p_L.shape[0]),
        "range_noise_m": faces.noise,
        "edge_m": cube.edge,
        "edge_tolerance_m": cube.edge_tolerance,
        "rms_range_error_m": float(np.sqrt(np.mean(res.fun**2))),
        "evaluations": int(res.nfev),
        "status": str(res.message),
    }


def range_size_fit(
    scan: SpinScan,
    start: Extrinsics,
    cube: CubeGeometry,
    *,
    platter_radius: float,
    estimate_ry: bool = True,
    range_model: RangeModelName = "offset",
    start_range: RangeModel = IDENTITY,
    incidence: bool = False,
    encoder: bool = False,
    gate: float | None = None,
) -> KnownSizeFit:
    """The known-size cube fit with the lidar's range model (DESIGN §9): H's tx, ty, tz, rz
    (and ry) and the range terms of ``range_model`` fitted to the cube's faces — the cube's
    edge and height are known lengths, its faces square to each other and to the platter —
    and to the platter top (the plane x_P = 0, which also fixes ty). A range offset turns the
    faces that face the rays at 45° (the platter and the top one way, the side faces the other)
    by about b/(2ρ); a scale error changes the cube's size (k·edge) and nothing else.

    The returns are chosen by their rays, not by where their noisy ranges put them
    (:func:`model_labels`): at this precision a choice that depends on the noise biases the
    offset (a static mask or a band around a face keeps the returns whose noise moved them in).

    σ as :func:`known_size_fit`'s; the bias bound carries the edge tolerance (which now also
    moves the scale error and the offset) and the faces' noise bias in ry. With ``encoder``,
    the result says how it follows the encoder's angle error (``encoder_direction``).

    Raises :class:`FineTuningError` for ``offset+scale`` on a cube not stated to be of the
    platter's finish (``cube.same_finish_as_platter``): the scale is read from the cube's height
    above the platter, and a platter that reads at another range (its reflectivity) would be
    taken for a scale error (2400 ppm, ty 2.8 mm off, on recipes/sim-realistic.yaml's).

    ``gate`` (m): raise :class:`FineTuningError` unless the cube's box under ``start`` is
    within this plus 6σ of range noise of the recipe's edge across (an axis offset δ widens it
    by about 2δ): the shape strategy fits from its start only a start that close, else from the
    box cost's result (:func:`calstation.engine.shape.shape_fine_tune_points`)."""
    if range_model == "offset+scale" and not cube.same_finish_as_platter:
        raise FineTuningError(
            "the known-size cube fit cannot measure the lidar's range scale error "
            "(range_model: offset+scale) with this cube: its height is read from the platter, "
            "which is not stated to be of the cube's finish "
            "(fixtures.qa_cube.same_finish_as_platter); fit the offset only, or state one finish")
    names = ["tx", "ty", "tz", "ry", "rz"] if estimate_ry else ["tx", "ty", "tz", "rz"]
    free = [PARAMETER_NAMES.index(n) for n in names] + estimated_indices(range_model,
                                                                          incidence)
    base = np.concatenate([start.with_(rx=0.0).as_vector(), start_range.as_vector()])
    cloud = segment_cube(start_range_points(scan.p_L, start_range), scan.phi,
                         start.with_(rx=0.0), cube.edge, platter_radius, most=FIRST_CLOUD)
    first, extents = _label_in_box(cloud, start.with_(rx=0.0))
    pose, noise = first.pose[:3], first.noise
    across = float(np.max(np.abs(extents[1:] - cube.edge)))
    if gate is not None and not across <= gate + 6.0 * noise:
        raise FineTuningError(
            f"the cube's box under the start is {across * 1e3:.1f} mm off its edge across, "
            f"beyond {(gate + 6.0 * noise) * 1e3:.1f} mm: the start is too far for the known-size "
            "fit alone")
    # the returns the rounds may label, with what does not change between them
    returns = _Returns.of(scan, _near_platter(scan, base, platter_radius))
    # a round on a part of the returns only moves the model the labels are chosen against: it
    # does that within a fraction of the last round's σ, in a fraction of the time. Rounds on
    # the same part go on until one moves H by less than SETTLED_M and SETTLED_RAD (two rounds
    # on a part and two on all of them differ by the part's own noise, up to 0.7 mm in ty);
    # then one round on all of them
    settled, moved = False, (math.inf, math.inf)
    for i in range(RANGE_ROUNDS):
        k = 1 if settled else FIRST_ROUNDS_STRIDE
        faces, platter = model_labels(returns.every(k), base, pose, cube.edge, platter_radius,
                                      noise, most=(FIT_POINTS // k, PLATTER_POINTS // k))
        # the platter's shape is fitted in the last round only, from a settled H: in the first
        # rounds, far from it, its dish would take up the error of the axis's tilt
        errors = RangeSizeErrors(faces, platter, base, free, cube.edge, dish=settled)
        x0 = np.concatenate([base[free], pose, np.zeros(errors.shape)])
        # TRF's steps, from the normal equations (calstation.engine.softl1)
        res = soft_l1_fit(errors, errors.jac, x0, f_scale=_f_scale(noise),
                          x_scale=_scales(free, x0.size - len(free)), max_nfev=MAX_NFEV)
        if settled:
            return _range_fit_result(res, errors, faces, free, cube, platter, encoder,
                                     platter_radius)
        moved = _moved(base, errors.vector(res.x))
        base, pose = errors.vector(res.x), res.x[len(free):len(free) + 3]
        settled = i > 0 and moved[0] < SETTLED_M and moved[1] < SETTLED_RAD
    raise FineTuningError(
        f"the known-size cube fit did not settle in {RANGE_ROUNDS} rounds: its last moved the "
        f"axis by {moved[0] * 1e3:.2f} mm and {math.degrees(moved[1]):.3f}°; its start (the "
        "shape strategy's box result, or the spin target's estimate at the cube stage) is too "
        "far off, see the recipe's start or the fixtures' placement")


def _moved(before: FloatArray, after: FloatArray) -> tuple[float, float]:
    """How far a round moved H (its parameter vectors before and after, the range terms beside
    them): the largest change of a translation (m) and of a rotation (rad)."""
    change = np.abs(after[: len(PARAMETER_NAMES)] - before[: len(PARAMETER_NAMES)])
    return float(np.max(change[:3])), float(np.max(change[3:]))


def start_range_points(p_L: FloatArray, model: RangeModel) -> FloatArray:
    """The returns ``p_L`` corrected by ``model`` (themselves when it is the identity)."""
    return p_L if model.is_identity else model.points(p_L)


def _scales(free: list[int], pose: int) -> FloatArray:
    """TRF's x_scale: a millimetre or a milliradian for H and the offset, 1e-4 for the scale
    error, a millimetre for the pose."""
    return np.array([1e-4 if i == SCALE else 1e-3 for i in free] + [1e-3] * pose)


def _range_fit_result(res: OptimizeResult, errors: RangeSizeErrors, faces: _Faces, free: list[int],
                      cube: CubeGeometry, platter: FloatArray, encoder: bool,
                      platter_radius: float) -> KnownSizeFit:
    """The :class:`KnownSizeFit` of :func:`range_size_fit`: σ from the block sandwich of the
    faces and the platter (× :data:`SIGMA_SCALE`, with the model floor), the bias bound in
    quadrature."""
    v = errors.vector(res.x)
    H = Extrinsics.from_vector(v[: len(PARAMETER_NAMES)])
    phi = np.arctan2(faces.sin, faces.cos)
    # the blocks by where the model puts each return (its ray at the model's range): blocks cut
    # by the noisy positions would split a surface's returns by the sign of their noise
    model = np.vstack([correct_vector(faces.p_L, v), correct_vector(platter, v)])
    model -= unit_rays(model) * np.asarray(res.fun)[:, None]
    n_faces = faces.p_L.shape[0]
    # faces in D (what turns with the cube), the platter in P (what stays with the lidar's rays)
    where = np.vstack([lidar_to_dynamic(model[:n_faces], phi, H), (model[n_faces:] - H.t) @ H.R])
    full = _block_covariance(res, where, free)
    cov = None if full is None else full[: len(free), : len(free)]
    edge = _edge_direction(res, errors, free, cube.edge_tolerance)
    bias = _bias_bound(res, errors, faces, free, cube.edge_tolerance, edge)
    return KnownSizeFit(
        H=H, sigma=_sigma_with_bias(cov, free, bias), covariance=covariance_record(cov, free),
        bias=bias, edge_direction=edge,
        details={**_details(res, faces, cube), "platter_returns": int(platter.shape[0]),
                 **_flatness(res, full, len(free) + 3, platter_radius),
                 "range_model": [ESTIMATED_NAMES[i] for i in free if i >= OFFSET]},
        range_model=RangeModel.from_vector(v), residuals=_residuals(res, errors, faces.p_L),
        encoder_direction=_encoder_direction(res, errors, free) if encoder else None,
    )


def _flatness(res: OptimizeResult, cov: FloatArray | None, at: int, radius: float) -> JSONObject:
    """The platter's flatness the fit measured (m, the depth of its dish, x[``at``], from the
    axis to the rim of ``radius``: positive, the rim higher) with its 1σ (NaN without a
    covariance)."""
    sigma = math.nan if cov is None else math.sqrt(max(float(cov[at, at]), 0.0))
    return {"platter_flatness_m": float(res.x[at]) * radius**2,
            "sigma_platter_flatness_m": sigma * radius**2}


def _encoder_direction(
    res: OptimizeResult, errors: RangeSizeErrors, free: list[int]
) -> dict[str, dict[str, float]]:
    """Per coefficient of the encoder's angle error (:mod:`calstation.engine.encoder`), how far
    each free parameter moves per radian of it: dx = −J⁺·∂r/∂c. A face return's residual
    depends on its own platter angle alone, so ∂r/∂c is ∂r/∂φ (one central difference of
    every angle turned alike) times the coefficient's harmonic at the return's angle; the
    platter's residuals do not turn with the angles."""
    from calstation.engine.encoder import HARMONICS, STEP, basis, turned

    f = errors.f
    moved = []
    for sign in (1.0, -1.0):
        cos, sin = turned(f.cos, f.sin, sign * STEP)
        moved.append(RangeSizeErrors(replace(f, cos=cos, sin=sin), errors.platter, errors.base,
                                      errors.free, errors.edge, errors.dish)(res.x))
    by_angle = (moved[0] - moved[1]) / (2.0 * STEP)
    columns = np.zeros((by_angle.size, len(HARMONICS)))
    n = f.cos.size
    columns[:n] = by_angle[:n, None] * basis(f.cos, f.sin)
    dx = _response(res, columns, errors.f.noise)[: len(free)]
    return {h: {ESTIMATED_NAMES[i]: float(dx[k, j]) for k, i in enumerate(free)}
            for j, h in enumerate(HARMONICS)}


def _residuals(
    res: OptimizeResult, errors: RangeSizeErrors, p_L: FloatArray
) -> dict[str, TrendRecord]:
    """The range fit's residuals on the cube's faces as range errors (m, positive: the return
    reads long) against each return's range, incidence angle and azimuth
    (:mod:`calstation.engine.residuals`). The platter's are left out: about their own mean
    when its level is free, they would put a step between the angles the platter is seen at
    and the faces'; and the faces, turning, are seen at every angle."""
    k = 0.0 if errors.level_free else float(errors.vector(res.x)[SCALE])
    n = errors.f.p_L.shape[0]
    error = np.asarray(res.fun, dtype=np.float64)[:n] / (1.0 + k)
    incidence = np.arccos(np.clip(np.abs(errors.cosines(res.x)[:n]), 0.0, 1.0))
    p_L = p_L[:n]
    return residual_trends(error, {
        "range": np.linalg.norm(p_L, axis=1), "incidence": incidence,
        "azimuth": np.arctan2(p_L[:, 0], p_L[:, 1])})


def _covariance(
    res: OptimizeResult, errors: RangeErrors, faces: _Faces, free: list[int]
) -> FloatArray | None:
    """(n, n) covariance of the free parameters of H, the part that falls with more data: the
    block sandwich × :data:`SIGMA_SCALE` and the model floor."""
    H = errors.H(res.x)
    p_D = lidar_to_dynamic(faces.p_L, np.arctan2(faces.sin, faces.cos), H)
    full = _block_covariance(res, p_D, free)
    return None if full is None else full[: len(free), : len(free)]


def _block_covariance(res: OptimizeResult, where: FloatArray, free: list[int]) -> FloatArray | None:
    """(m, m) covariance of every parameter of the fit ``res`` (the ``free`` ones of H and the
    range model first, then the cube's pose and the rest), its residuals correlated within the
    spatial blocks of the points ``where`` (the block sandwich) × :data:`SIGMA_SCALE`, with the
    model floor on the ``free`` ones; None when it cannot be computed."""
    full = parameter_covariance(res, list(range(res.x.size)), blocks=block_ids(where, SIGMA_BLOCK))
    if full is None:
        return None
    n = len(free)
    out: FloatArray = full * SIGMA_SCALE**2
    out[:n, :n] += model_floor(free)
    return out


def _f_scale(noise: float) -> float:
    """The soft-L1 loss's scale (m) of a fit on faces of range ``noise``: residuals beyond it
    (mixed pixels, strays) count less and less."""
    return max(0.002, 3.0 * noise)


def _response(res: OptimizeResult, columns: FloatArray, noise: float) -> FloatArray:
    """(n, k) how the fit ``res`` (soft-L1, :func:`_f_scale` of ``noise``) moves per unit of
    each of k things that move its residuals by ``columns`` (m, k): dx = −J⁺·w·∂r, with ``J``
    the loss's Jacobian (``res.jac``, each row scaled by √w) and w its Gauss–Newton weights,
    ρ′(z) + 2z·ρ″(z) at z = (r/f_scale)² (scipy's own scaling)."""
    weight = gauss_newton_weight((np.asarray(res.fun) / _f_scale(noise)) ** 2)
    dx: FloatArray = -np.linalg.lstsq(np.asarray(res.jac), columns * weight[:, None],
                                      rcond=None)[0]
    return dx


def _edge_direction(
    res: OptimizeResult, errors: RangeErrors | RangeSizeErrors, free: list[int], tolerance: float
) -> dict[str, float]:
    """Per free parameter, the signed move (m, rad) of a cube ``tolerance`` larger than the
    recipe's edge: dx = −J⁺·∂r/∂edge·tolerance."""
    if tolerance <= 0:
        return {ESTIMATED_NAMES[i]: 0.0 for i in free}
    step = 1e-5
    dr = (errors(res.x, errors.edge + step) - errors(res.x)) / step
    dx = _response(res, dr[:, None], errors.f.noise)[: len(free), 0]
    return {ESTIMATED_NAMES[i]: float(dx[k]) * tolerance for k, i in enumerate(free)}


def _bias_bound(
    res: OptimizeResult, errors: RangeErrors | RangeSizeErrors, faces: _Faces, free: list[int],
    tolerance: float, edge: dict[str, float] | None = None,
) -> dict[str, float]:
    """Per parameter, a bound on what more data does not remove (m, rad): the edge tolerance
    moved through the fit (|dx| with dx = −J⁺·∂r/∂edge·tolerance) and, in ry, the range
    errors' noise bias on the faces (the twist's: +0.08–0.10° at 2 mm)."""
    if edge is None:
        edge = _edge_direction(res, errors, free, tolerance)
    out = {k: abs(v) for k, v in edge.items()}
    if RY in free:
        out["ry"] += range_twist_bias(faces.noise)
    return out
