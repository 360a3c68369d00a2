"""Shape-constrained fine-tuning on the QA cube (paper §III-B-1, §IV-B; DESIGN §5).

For a candidate H the cube's spin scan is reconstructed in frame D, segmented above the platter
(threshold along X_P with a 1 cm margin), cleaned by radius outlier removal (fewer than 8
neighbours within 1 mm → dropped) and enclosed by Open3D's minimum-volume oriented bounding box.
The cost is ``C1 + C2``: C1 the mean squared signed distance of the points to the nearest box
face, C2 = Σ(s_i − s)² the squared deviation of the box edges from the true edge. SciPy's TRF
minimises it within ±20 mm / ±2° of the start (xtol 1e-12, ftol 1e-10, 100 evaluations).

calstation additions (docs/algorithms.md): a fixed random subset of the raw returns (the outlier
radius scaled with the density, so the neighbour count keeps its meaning) for speed; a finite
difference step relative to each parameter (:data:`DIFF_STEP`); ty held at its start while
fitting (the cube, like the periodicity cost, cannot see a shift along the axis), and the
result's origin then moved along the axis onto the platter top seen in the cube scan (the
DESIGN §2 gauge, :func:`_platter_gauge`); the expected height
of the box is ``s − margin`` (the segmentation cuts the bottom off); by default an *upright* box
(one axis along X_D: the cube stands on the platter) whose faces are the medians of the points
near them instead of the extremes, which removes the ~3σ noise inflation of the extremes from
C2; and ry taken from the flatness of the cube's faces (an ry error twists them), alternating
with the box solve of tx, tz and rz, because the box cost's own ry minimum is biased by a few
tenths of a degree; and, last, a rigid cube of the recipe's edge fitted to the faces with H
(:mod:`calstation.engine.cubefit`): the cube's size places the axis where the box cost's blur
could not. ``box="minimal"`` keeps the paper's Open3D box and joint solve.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from calstation.engine.cube import check_cube_points
from calstation.engine.frames import PARAMETER_NAMES, Extrinsics, FloatArray, lidar_to_dynamic
from calstation.engine.geometry import face_labels, minimal_obb, upright_box
from calstation.engine.periodicity import block_ids, parameter_sigma, periodicity_fine_tune_scan
from calstation.engine.rangemodel import RangeModelName
from calstation.engine.result import CalibrationResult
from calstation.engine.settings import (
    DEFAULT_PLATTER_RADIUS,
    CubeGeometry,
    PeriodicitySettings,
    QALimits,
    ShapeSettings,
)
from calstation.engine.shapecost import (  # ShapeCost lived here; still importable from it
    ShapeCost as ShapeCost,
    near_cube,
    subsample,
)
from calstation.engine.shapesize import from_start, with_known_size
from calstation.engine.spinscan import SpinScan, from_recording, prepare
from calstation.engine.twist import FaceFlatness, face_range_noise, flatness_ry_sigma
from calstation.errors import FineTuningError, VerificationError

if TYPE_CHECKING:
    from scipy.optimize import OptimizeResult

    from calstation.engine.scan import Scan

Progress = Callable[[str, float], None]

DIFF_STEP = 1e-4
"""SciPy's ``diff_step``: relative to each parameter's value (~0.3–0.6 µm in tx and tz, ~0.08
mrad in rz at a typical start; docs/algorithms.md)."""
COARSE_STAGES = 2
"""Periodicity stages (20 and 10 mm cells) run on the cube scan before the shape cost."""
FREE = ("tx", "tz", "ry", "rz")
"""Parameters the shape strategy can estimate; ty is the gauge (held at its start)."""
RY = PARAMETER_NAMES.index("ry")
"""Index of ry in an H vector."""


@dataclass(frozen=True)
class _BoxLook:
    """How the cube looks under an H: the box cost and how far the plain (extreme-point) box's
    horizontal edges are from the cube's."""

    cost: float
    """C1 + C2 of the upright box (m²); inf when no cube is found above the platter"""
    edge_excess: float
    """max |extent − s| of the plain box's two horizontal edges (m); inf without a cube"""


def _box_look(
    p_L: FloatArray,
    phi: FloatArray,
    H: Extrinsics,
    cube: CubeGeometry,
    settings: ShapeSettings,
    platter_radius: float,
    max_points: int,
) -> _BoxLook:
    """:class:`_BoxLook` of the cube scan's moving returns ((N, 3) in L, (N,) φ) under H."""
    p_L, phi = near_cube(p_L, phi, H, cube, platter_radius)
    if p_L.shape[0] < 200:
        return _BoxLook(math.inf, math.inf)
    p_L, phi, density_scale = subsample(p_L, phi, max_points)
    cost = ShapeCost(
        p_L, phi, cube, settings, platter_radius=platter_radius, density_scale=density_scale
    )
    cost.freeze(H)  # one segmentation for the cost and the plain box
    r = cost.residuals_of(H)
    if cost._frozen_idx is None or cost._frozen_idx.size < 50:
        return _BoxLook(math.inf, math.inf)
    _, _, extents = upright_box(cost.to_dynamic(H, cost._frozen_idx), robust=False)
    return _BoxLook(
        float(np.sum(r[:-3] ** 2) + np.sum(cost.last_edge_errors**2)),
        float(np.max(np.abs(extents[1:] - cube.edge))),
    )


COARSE_GATE_M = 0.005
"""The coarse alignment runs when the start's plain box is more than this plus 6 σ of range
noise off the cube's edge (m): an offset δ of the axis widens it by ~2δ, so starts within a few
millimetres, well inside the box cost's reach, skip it."""


def _coarse_alignment(
    scan: SpinScan,
    p_mov: FloatArray,
    phi_mov: FloatArray,
    start: Extrinsics,
    cube: CubeGeometry,
    settings: ShapeSettings,
    *,
    platter_radius: float,
    max_points: int,
) -> tuple[Extrinsics, dict[str, object]]:
    """A far start brought within the box cost's reach, and what was done.

    The box cost has no basin wider than the cube: the coarse stages of the periodicity
    matching run on the cube's own scan (ty and ry held) unless the start already shows the
    cube's size (:data:`COARSE_GATE_M`). The two half-turns of a cube see different faces,
    which biases that matching at low pitch, so the alignment is kept only where the box fits
    better than at the start.
    """
    look = _box_look(p_mov, phi_mov, start, cube, settings, platter_radius, max_points)
    noise = scan.noise if math.isfinite(scan.noise) else 0.001
    gate = COARSE_GATE_M + 6.0 * noise
    if look.edge_excess <= gate:
        return start, {
            "used": False,
            "needed": False,
            "start_edge_excess_m": look.edge_excess,
            "gate_m": gate,
        }
    skipped = []
    for n_stages in range(COARSE_STAGES, 0, -1):
        try:
            pre = periodicity_fine_tune_scan(
                scan,
                start,
                PeriodicitySettings(gauge="ty"),
                platter_radius=platter_radius,
                stages=n_stages,
            )
        except FineTuningError as exc:
            skipped.append(str(exc))
            continue
        aligned = pre.H.with_(ty=start.ty, ry=start.ry, rx=0.0)
        after = _box_look(p_mov, phi_mov, aligned, cube, settings, platter_radius, max_points)
        report = {
            "used": after.cost < look.cost,
            "needed": True,
            "start_edge_excess_m": look.edge_excess,
            "gate_m": gate,
            "stages": n_stages,
            "start": start.as_dict(),
            "aligned": aligned.as_dict(),
            "box_cost_start": look.cost,
            "box_cost_aligned": after.cost,
            "seconds": pre.timings["total"],
            "skipped": skipped,
        }
        return (aligned if after.cost < look.cost else start), report
    return start, {"used": False, "needed": True, "skipped": skipped}


BOX_NOISE_M = 0.0003
"""Empirical σ of the box cost's axis per 1 mm of range noise (metres), beyond what its
residuals and the cube's dimensions show (see :func:`axis_sigma_floor`)."""


def axis_sigma_floor(edge_error: float, noise: float) -> float:
    """The part of the shape strategy's tx and tz σ (m) its cost's residuals cannot see.

    An axis offset δ doubles each side face of the reconstructed cube about 2δ apart, so the
    face-fit edges come out ≈ 2δ too long: ``edge_error`` (m, the cube check's
    ``edge_error`` under the result) / 2 bounds the offset the cube's known size allows. To it
    is added :data:`BOX_NOISE_M`·(σ_noise / 1 mm), ``noise`` in metres. On the shape sweep of
    docs/algorithms.md (60 runs, 0.5 and 1 mm of noise, 180–1000 lines/s) the axis offset
    stayed within 1.9 of the resulting σ; the residual sandwich alone had let 1–3 mm offsets
    pass with σ of 0.02–0.09 mm. ``edge_error`` NaN (the cube could not be dimensioned): the
    whole cube edge is the bound.
    """
    dims = 0.5 * edge_error if math.isfinite(edge_error) else 0.1
    spread = BOX_NOISE_M * noise / 0.001 if math.isfinite(noise) and noise > 0 else 0.0
    return math.hypot(dims, spread)


RZ_NOISE_RAD_PER_M = 0.25
RZ_NOISE_RAD_PER_M2 = 230.0
"""The box cost's bias in rz (rad) per metre and per square metre of range noise, beyond what
its residuals show (see :func:`rz_sigma_floor`)."""


def rz_sigma_floor(noise: float) -> float:
    """The part of the shape strategy's rz σ (rad) its cost's residuals cannot see.

    The box cost's faces are medians of noisy returns, and their bias tilts the fitted axis in
    the scan plane: on the shape sweeps of docs/algorithms.md (0.5, 1 and 2 mm of range noise,
    180–1000 lines/s, the nine scenarios plus 0.9 m / 40°) the rz error reached 0.025°, 0.07°
    and 0.24° while the residual sandwich said 0.001–0.01°. ``noise`` (m): the range noise on
    the cube's faces; 0 when it is unknown.
    """
    if not math.isfinite(noise) or noise <= 0:
        return 0.0
    return RZ_NOISE_RAD_PER_M * noise + RZ_NOISE_RAD_PER_M2 * noise**2


def _shape_pass(
    scan: SpinScan,
    start: Extrinsics,
    cube: CubeGeometry,
    settings: ShapeSettings,
    *,
    platter_radius: float,
    max_points: int,
    box: str,
    estimate_ry: bool,
    coarse: bool,
    progress: Progress | None,
    flatness_ry: bool = True,
) -> CalibrationResult:
    """One pass of :func:`shape_fine_tune_points` (coarse alignment, box, faces) from
    ``start`` on the prepared cube scan; ``flatness_ry``: see :func:`_solve`."""
    start = start.with_(rx=0.0)
    # the platter ring and the background are static in L: they never belong to the cube
    moving = ~scan.static
    p_mov, phi_mov = scan.p_L[moving], scan.phi[moving]
    coarse_report: dict[str, object] = {"used": False, "needed": None}
    if coarse:
        start, coarse_report = _coarse_alignment(
            scan,
            p_mov,
            phi_mov,
            start,
            cube,
            settings,
            platter_radius=platter_radius,
            max_points=max_points,
        )
    # all of them near the cube: the face-flatness ry step needs the density
    p_L_near, phi_near = near_cube(p_mov, phi_mov, start, cube, platter_radius)
    n_all = p_L_near.shape[0]
    if n_all < 200:
        raise FineTuningError(
            f"only {n_all} returns above the platter in the cube scan; is the QA cube "
            "on the platter?"
        )
    p_L, phi, density_scale = subsample(p_L_near, phi_near, max_points)
    cost = ShapeCost(
        p_L,
        phi,
        cube,
        settings,
        platter_radius=platter_radius,
        density_scale=density_scale,
        box=box,
    )
    fit = _BoxFit(cost, p_L_near, phi_near, start, settings, box, progress)
    solved = _solve(fit, estimate_ry, flatness_ry)
    return _pass_result(fit, solved, estimate_ry, coarse_report, n_all)


class _BoxFit:
    """The estimate of one shape pass, ``x6`` (moved in place), and the two solves that move
    it: the box cost over some of tx, tz, ry and rz, and ry from the cube faces' flatness.

    ``p_L_near``, ``phi_near``: every moving return near the cube ((N, 3) in L, (N,) φ), which
    the flatness step needs at full density; the box cost works on its own subset.
    """

    def __init__(
        self,
        cost: ShapeCost,
        p_L_near: FloatArray,
        phi_near: FloatArray,
        start: Extrinsics,
        settings: ShapeSettings,
        box: str,
        progress: Progress | None,
    ) -> None:
        self.cost = cost
        self.p_L_near, self.phi_near = p_L_near, phi_near
        self.settings = settings
        self.box = box
        self.progress = progress
        self.x6 = start.as_vector()
        self.start6 = self.x6.copy()
        self.tb = settings.translation_bound
        self.rb = math.radians(settings.rotation_bound_deg)

    def solve(self, names: tuple[str, ...], nfev: int, settled: bool = False) -> OptimizeResult:
        """The box cost over the parameters ``names``, at most ``nfev`` evaluations, within the
        bounds around the start; returns SciPy's last ``least_squares`` result. With
        ``settled`` (the known-size cube fit follows), the upright box's solves stop once one
        after the first moves the estimate by less than :data:`START_SETTLED_M` and
        :data:`START_SETTLED_RAD`."""
        cost, settings, progress, box, x6 = (
            self.cost, self.settings, self.progress, self.box, self.x6)
        idx = [PARAMETER_NAMES.index(n) for n in names]
        base = x6.copy()

        def fun(x: FloatArray) -> FloatArray:
            if progress is not None:
                progress("shape fine-tuning", min(1.0, cost.evaluations / settings.max_nfev))
            v = base.copy()
            v[idx] = x
            return cost.residuals_of(Extrinsics.from_vector(v))

        half = np.array([self.tb if i < 3 else self.rb for i in idx])
        centre = self.start6[idx]
        used = 0
        r: OptimizeResult | None = None
        # upright: outer loop re-segmenting between inner solves on a fixed point set;
        # minimal (paper): one solve re-segmenting at every evaluation
        chunk = max(len(idx) + 2, 3 * (len(idx) + 1)) if box == "upright" else nfev
        limit = np.array([START_SETTLED_M if i < 3 else START_SETTLED_RAD for i in idx])
        solves = 0
        while used < nfev:
            if box == "upright":
                cost.freeze(Extrinsics.from_vector(x6))
            before = cost.evaluations
            x0 = np.clip(x6[idx], centre - half + 1e-12, centre + half - 1e-12)
            r = least_squares(
                fun,
                x0,
                bounds=(centre - half, centre + half),
                method="trf",
                xtol=settings.xtol,
                ftol=settings.ftol,
                max_nfev=min(chunk, nfev - used),
                diff_step=DIFF_STEP,
                x_scale=np.full(len(idx), 1e-3),
            )
            used += max(1, cost.evaluations - before)
            solves += 1
            step = np.abs(r.x - x6[idx])
            x6[idx] = r.x
            if box != "upright" or (step.max() < 1e-6):
                break
            if settled and solves > 1 and np.all(step < limit):
                break
        cost.freeze(None)
        return r

    def labelled_faces(
        self, H: Extrinsics
    ) -> tuple[FloatArray, FloatArray, list[NDArray[np.bool_]]]:
        """The returns near the cube's faces under H (in L, their φ) and a mask per face."""
        p_L_near, phi_near = self.p_L_near, self.phi_near
        p_D, mask = self.cost.cloud(H)
        if int(mask.sum()) < 50:
            raise FineTuningError("too few cube returns to estimate ry from the faces")
        labels = face_labels(lidar_to_dynamic(p_L_near, phi_near, H), *upright_box(p_D[mask]))
        keep = labels >= 0
        pts_L, ph, labels = p_L_near[keep], phi_near[keep], labels[keep]
        faces = [labels == f for f in np.unique(labels) if np.count_nonzero(labels == f) >= 30]
        return pts_L, ph, faces

    def planar_ry(self) -> tuple[float, float]:
        """ry from the cube faces' own flatness; (ry, 1σ) in rad.

        Fits tz, ry and rz to the returns near each face (labelled by the upright box under
        the current H, a plane per face re-fitted at every evaluation, soft-L1 loss against
        mixed pixels) and keeps ry only: tz and rz also bend the faces, so they are freed here,
        but the box cost places them better.
        """
        x6, tb, rb = self.x6, self.tb, self.rb
        H = Extrinsics.from_vector(x6)
        pts_L, ph, faces = self.labelled_faces(H)
        if not faces:
            raise FineTuningError("no cube face has enough returns to estimate ry")
        idx = [PARAMETER_NAMES.index(n) for n in ("tz", "ry", "rz")]
        base = x6.copy()
        faces_L, faces_phi = [pts_L[sel] for sel in faces], [ph[sel] for sel in faces]
        flat = FaceFlatness(faces_L, faces_phi)

        def flatness(x: FloatArray) -> FloatArray:
            v = base.copy()
            v[idx] = x
            return flat(Extrinsics.from_vector(v))

        centre = self.start6[idx]
        # a set-B start is 2° off and the true ry up to 0.5° from the initial 0 (as periodicity)
        half = np.array([tb, max(rb, math.radians(2.5)), rb])
        r = least_squares(
            flatness,
            np.clip(base[idx], centre - half + 1e-12, centre + half - 1e-12),
            bounds=(centre - half, centre + half),
            method="trf",
            loss="soft_l1",
            f_scale=0.002,
            diff_step=DIFF_STEP,
            x_scale=np.full(3, 1e-3),
            max_nfev=self.settings.max_nfev,
        )
        # σ as the cube check's twist's
        Hr = Extrinsics.from_vector(np.where(np.arange(6) == RY, r.x[1], x6))
        return float(r.x[1]), flatness_ry_sigma(r, idx, faces_L, faces_phi, Hr)


START_SETTLED_M = 0.0005
START_SETTLED_RAD = 0.0005
"""Before the known-size cube fit, the upright box's solves stop once one (after the first)
moves tx and tz by less than this (m) and rz by less than this (rad): re-segmented between its
solves, the box cost wanders by a few tenths of a millimetre about its minimum (its last
solves of 100 evaluations moved it 0.3–0.6 mm on the default scene), and the fit settles from
a start within a few millimetres. About half the box cost's evaluations."""


@dataclass(frozen=True)
class _Solved:
    """What the solves of a pass leave for its result."""

    res: OptimizeResult
    """SciPy's last ``least_squares`` result of the box cost"""
    free: list[int]
    """the indices of the parameters that result solved for"""
    ry_rounds: list[dict[str, float]]
    """ry and its change per round of the face-flatness step (empty: ry from the box cost or
    held)"""
    ry_sigma: float
    """1σ of ry from the last face-flatness step (rad; NaN without one)"""


def _solve(fit: _BoxFit, estimate_ry: bool, flatness_ry: bool = True) -> _Solved:
    """Run the pass's solves on ``fit``: with the upright box and ``estimate_ry``, tx, tz, rz
    from the box alternating with ry from the faces (without ``flatness_ry``, tx, tz, rz only:
    the known-size cube fit that follows estimates ry); with the minimal box, the paper's joint
    solve; without ``estimate_ry``, tx, tz, rz with ry held."""
    settings = fit.settings
    names = FREE if estimate_ry else ("tx", "tz", "rz")
    free = [PARAMETER_NAMES.index(n) for n in names]
    ry_rounds: list[dict[str, float]] = []
    ry_sigma = math.nan
    if estimate_ry and fit.box == "upright":
        # the box cost is nearly flat and jumpy in ry: settle tx, tz, rz with ry held, then
        # alternate ry from the faces' flatness with tx, tz, rz from the box
        res = fit.solve(("tx", "tz", "rz"), settings.max_nfev, settled=not flatness_ry)
        for _ in range(2 if flatness_ry else 0):
            ry, ry_sigma = fit.planar_ry()
            change = abs(ry - fit.x6[RY])
            fit.x6[RY] = ry
            res = fit.solve(("tx", "tz", "rz"), max(4, settings.max_nfev // 2))
            ry_rounds.append({"ry_rad": ry, "change_rad": change})
            if change < math.radians(0.005):
                break
        free = [PARAMETER_NAMES.index(n) for n in ("tx", "tz", "rz")]
    elif estimate_ry:
        # the paper's joint solve; tz and ry twist the cloud alike, so settle the sharp
        # parameters with ry held first
        fit.solve(("tx", "tz", "rz"), settings.max_nfev // 2)
        res = fit.solve(FREE, settings.max_nfev - settings.max_nfev // 2)
    else:
        res = fit.solve(names, settings.max_nfev)
    return _Solved(res, free, ry_rounds, ry_sigma)


def _pass_result(
    fit: _BoxFit,
    solved: _Solved,
    estimate_ry: bool,
    coarse_report: dict[str, object],
    n_all: int,
) -> CalibrationResult:
    """The pass's :class:`CalibrationResult` at ``fit``'s estimate: the cost's terms, σ
    (cluster-robust over the box cost's residuals; ry's from the faces when they gave it), the
    range noise on the faces and the box's extents."""
    cost, box = fit.cost, fit.box
    H = Extrinsics.from_vector(fit.x6)
    final = cost.residuals_of(H)
    c1 = float(np.sum(final[:-3] ** 2))
    c2 = float(np.sum(cost.last_edge_errors**2))
    total = float(np.sum(final**2))
    sigma = _box_sigma(cost, H, solved)
    pts_L, ph, faces = fit.labelled_faces(H)
    noise = face_range_noise([pts_L[f] for f in faces], [ph[f] for f in faces], H)
    if solved.ry_rounds:
        sigma["ry"] = solved.ry_sigma
    p_D, mask = cost.cloud(H)
    _, _, extents = (upright_box if box == "upright" else minimal_obb)(p_D[mask])
    if fit.progress is not None:
        fit.progress("shape fine-tuning", 1.0)
    res = solved.res
    return CalibrationResult(
        H=H,
        sigma=sigma,
        cost=total,
        iterations=int(res.nfev),
        strategy="shape",
        timings={},
        diagnostics={
            "gauge": "ty",
            "range_noise_m": noise,
            "gauge_note": "ty held at its start value (the cube cannot see a shift along the axis)",
            "box": box,
            "estimate_ry": estimate_ry,
            "ry_source": (
                ("face flatness" if box == "upright" else "box cost") if estimate_ry else "held"
            ),
            "ry_rounds": solved.ry_rounds,
            "coarse": coarse_report,
            "C1": c1,
            "C2": c2,
            "cost_terms": "C1 + C2" if box == "minimal" else "C1",
            "obb_extents_m": np.sort(extents).tolist(),
            "points_used": int(cost.p_L.shape[0]),
            "points_above_platter": int(n_all),
            "cube_points": int(mask.sum()),
            "outlier_radius_m": cost.outlier_radius,
            "evaluations": int(cost.evaluations),
            "status": str(res.message),
        },
    )


def _box_sigma(cost: ShapeCost, H: Extrinsics, solved: _Solved) -> dict[str, float]:
    """1σ per parameter of the last box solve at H."""
    # the box cost's residuals are neighbours on one shape: a cluster-robust σ over 2 cm blocks
    # (the three edge residuals are blocks of their own)
    blocks = block_ids(cost.to_dynamic(H), 0.02)
    blocks = np.concatenate([blocks, blocks.max(initial=-1) + 1 + np.arange(3)])
    return parameter_sigma(solved.res, solved.free, blocks=blocks)


def shape_fine_tune_points(
    p_L: FloatArray,
    phi: FloatArray,
    start: Extrinsics,
    cube: CubeGeometry,
    settings: ShapeSettings = ShapeSettings(),
    *,
    platter_radius: float = DEFAULT_PLATTER_RADIUS,
    max_points: int = 20_000,
    box: str = "upright",
    estimate_ry: bool = True,
    coarse: bool = True,
    known_size: bool = True,
    progress: Progress | None = None,
    scan: SpinScan | None = None,
    range_model: RangeModelName = "none",
    incidence: bool = False,
    encoder: bool = False,
) -> CalibrationResult:
    """Shape-constrained fine-tuning on the returns of the QA cube's spin scan.

    ``p_L`` (N, 3) returns in L (m), ``phi`` (N,) platter angles (rad). ``box``: ``"upright"``
    (calstation's default: a box standing on the platter) or ``"minimal"`` (the paper's
    minimum-volume OBB from Open3D). ``estimate_ry``: with the upright box, ry from the faces'
    flatness alternating with the box solve of tx, tz, rz; with the minimal box, the paper's
    joint solve; ``False`` holds ry at its start. ``coarse``: align a far start first with the
    coarse periodicity stages on the same scan; when only the coarsest stage could run (the
    start's ry too far off for the second), the whole pass is repeated from its result
    (docs/algorithms.md). ``known_size``: finish with an upright cube of the recipe's edge
    fitted to the labelled faces (:mod:`calstation.engine.cubefit`; tx, tz, rz and, with
    ``estimate_ry``, ry; σ from that fit). ``scan``: the same returns already prepared
    (:mod:`calstation.engine.spinscan`). ``range_model``: the lidar's range terms the
    known-size fit estimates with H (:func:`calstation.engine.cubefit.range_size_fit`; the box
    cost before it reads the ranges as measured), and the incidence bias with ``incidence``;
    with ``encoder``, how that fit follows the encoder's angle error
    (``diagnostics["follows_encoder"]``); with it, a start whose cube is within the coarse gate
    (:data:`COARSE_GATE_M`) is fitted from itself, without the box cost
    (:func:`calstation.engine.shapesize.from_start`). Returns a :class:`CalibrationResult` with
    strategy ``"shape"`` and cost ``C1 + C2`` (m²), or with the range model the known-size
    fit's mean squared range error (m²).
    """
    t0 = time.perf_counter()
    p_L = np.asarray(p_L, dtype=np.float64)
    phi = np.asarray(phi, dtype=np.float64).reshape(-1)
    if p_L.ndim != 2 or p_L.shape[1] != 3 or p_L.shape[0] != phi.shape[0]:
        raise FineTuningError(
            f"shape needs (N, 3) returns and (N,) angles, got {p_L.shape} and {phi.shape}"
        )
    prepared = prepare(p_L, phi) if scan is None else scan
    one_pass = partial(
        _shape_pass, prepared, cube=cube, settings=settings, platter_radius=platter_radius,
        max_points=max_points, box=box, estimate_ry=estimate_ry, coarse=coarse,
        progress=progress,
    )
    # the known-size fit estimates ry itself: the faces' flatness rounds before it changed
    # nothing but the time (docs/performance.md); they run when it cannot label the faces
    flatness = not (known_size and estimate_ry and box == "upright")
    if not flatness and range_model != "none" and coarse:
        # a start close enough: the known-size fit from it, without the box cost
        direct = from_start(prepared, start, cube, platter_radius, COARSE_GATE_M, range_model,
                            incidence, encoder)
        if direct is not None:
            direct.timings["total"] = time.perf_counter() - t0
            return direct
    result = _finish(_box_passes(one_pass, start, coarse, flatness), prepared, cube,
                     platter_radius, estimate_ry, known_size, range_model, incidence, encoder)
    if not flatness and not result.diagnostics["known_size"]["used"]:
        reason = result.diagnostics["known_size"]
        result = _finish(_box_passes(one_pass, start, coarse, True), prepared, cube,
                         platter_radius, estimate_ry, known_size=False)
        result.diagnostics["known_size"] = reason
    result.timings["total"] = time.perf_counter() - t0
    return result


def _box_passes(
    one_pass: Callable[..., CalibrationResult], start: Extrinsics, coarse: bool, flatness: bool
) -> CalibrationResult:
    """The box cost's result from ``start``: one pass, or two when the first's coarse
    alignment could run only its coarsest stage (the start's ry too far off for the second)."""
    result = one_pass(start, flatness_ry=flatness)
    passes = 1
    report = result.diagnostics["coarse"]
    if coarse and report.get("used") and report.get("stages", COARSE_STAGES) < COARSE_STAGES:
        result = one_pass(result.H, flatness_ry=flatness)
        passes = 2
    result.diagnostics["passes"] = passes
    return result


def _finish(
    result: CalibrationResult,
    prepared: SpinScan,
    cube: CubeGeometry,
    platter_radius: float,
    estimate_ry: bool,
    known_size: bool,
    range_model: RangeModelName = "none",
    incidence: bool = False,
    encoder: bool = False,
) -> CalibrationResult:
    """The box cost's ``result`` finished: the known-size cube fit (when asked), the σ floors
    of the box cost (without it), and the origin moved onto the platter top (the gauge; the
    fit with a range model fixes it itself, from the platter's returns)."""
    fitted = None
    if known_size or range_model != "none":
        result, fitted = with_known_size(result, prepared, cube, platter_radius, estimate_ry,
                                          range_model, incidence, encoder)
    if fitted is not None and range_model != "none":
        return result
    if range_model != "none":
        raise FineTuningError(
            "the lidar's range model (calibration.range_model) is estimated by the known-size "
            f"cube fit, which failed: {result.diagnostics['known_size']['reason']}"
        )
    # where the platter top lies along the axis, and (without the known-size fit) what the box
    # cost's residuals cannot see: the cube's own dimensions under the result; after the
    # known-size fit, on the cube's returns it found (under the box cost's H, < 1 mm away)
    level = math.nan
    try:
        check = check_cube_points(
            prepared.p_L, prepared.phi, result.H, cube, QALimits(),
            platter_radius=platter_radius, edges_only=True, memo=prepared.memo,
            nearby=fitted is not None,
        )
        edge_error, level = check.edge_error, check.platter_level
    except VerificationError:
        edge_error = math.nan
    result.diagnostics["edge_error_m"] = edge_error
    if fitted is None:
        noise = float(result.diagnostics.get("range_noise_m", math.nan))
        floor = axis_sigma_floor(edge_error, noise)
        for name in ("tx", "tz"):
            result.sigma[name] = math.hypot(result.sigma[name], floor)
        result.sigma["rz"] = math.hypot(result.sigma["rz"], rz_sigma_floor(noise))
    if math.isfinite(level):
        result = _platter_gauge(result, level)
    return result


PLATTER_LEVEL_SIGMA = 0.00005
"""1σ (m) of the platter top's level seen in the cube scan (the median of thousands of its
returns; what remains is the platter's own flatness)."""


def _platter_gauge(result: CalibrationResult, level: float) -> CalibrationResult:
    """``result`` with its origin moved along the axis onto the platter top seen in the cube
    scan (``level``, m along X_P under its H): the DESIGN §2 gauge.

    The box cost cannot see a shift along the axis, and ty is held at its start, so the origin
    along the axis stayed where the initial calibration put it: at 1.4 m / 35° the cube scan's
    platter lay 3–6 mm from x_P = 0 under the shape H, and tx carried that (tx errors of
    −5.6 to +3.1 mm for axis offsets of 0.1–1 mm). The shift changes tx and ty (and tz a
    little); their σ become the axis offset's σ (the held-ty σ_tx across the axis) and the
    level's (:data:`PLATTER_LEVEL_SIGMA`) along it.
    """
    H = result.H
    a = H.axis_direction()
    t = H.t + level * a
    result = replace(result, H=H.with_(tx=float(t[0]), ty=float(t[1]), tz=float(t[2])))
    # σ_tx (ty held) moved the axis across itself by σ_tx·|e_x·u|, u ⟂ a in the scan plane
    u = np.array([-a[1], a[0], 0.0])
    u /= max(float(np.linalg.norm(u)), 1e-12)
    across = result.sigma["tx"] * abs(u[0])
    before = result.sigma["tx"]
    for i, name in enumerate(("tx", "ty")):
        result.sigma[name] = math.hypot(across * u[i], PLATTER_LEVEL_SIGMA * a[i])
    record = result.diagnostics.get("covariance")
    if record and "tx" in record["parameters"] and before > 0:
        # tx's share of the covariance keeps its correlations at its new σ
        k = record["parameters"].index("tx")
        scale = np.ones(len(record["parameters"]))
        scale[k] = result.sigma["tx"] / before
        matrix = np.asarray(record["matrix"]) * np.outer(scale, scale)
        result.diagnostics["covariance"] = {**record, "matrix": matrix.tolist()}
    result.diagnostics["platter_level_m"] = level
    result.diagnostics["gauge"] = "platter"
    result.diagnostics["gauge_note"] = (
        "origin along the axis moved onto the platter top seen in the cube scan"
    )
    return result


def shape_fine_tune(
    recording: Scan,
    start: Extrinsics,
    cube: CubeGeometry,
    settings: ShapeSettings = ShapeSettings(),
    *,
    platter_radius: float = DEFAULT_PLATTER_RADIUS,
    box: str = "upright",
    estimate_ry: bool = True,
    coarse: bool = True,
    known_size: bool = True,
    progress: Progress | None = None,
    range_model: RangeModelName = "none",
    incidence: bool = False,
    encoder: bool = False,
) -> CalibrationResult:
    """Shape-constrained fine-tuning on a QA-cube spin-scan recording."""
    scan = from_recording(recording)
    try:
        return shape_fine_tune_points(
            scan.p_L,
            scan.phi,
            start,
            cube,
            settings,
            platter_radius=platter_radius,
            box=box,
            estimate_ry=estimate_ry,
            coarse=coarse,
            known_size=known_size,
            progress=progress,
            scan=scan,
            range_model=range_model,
            incidence=incidence,
            encoder=encoder,
        )
    except FineTuningError as exc:
        raise FineTuningError(f"{recording.path}: {exc}") from None
