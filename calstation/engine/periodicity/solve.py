"""The periodicity fine-tuning itself: the stages of the coarse-to-fine schedule run one after
the other, each an outer loop of matching and solving, and the result with its σ."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, TypedDict

import numpy as np
from scipy.optimize import least_squares

from calstation.engine.frames import Extrinsics, FloatArray
from calstation.engine.periodicity.cells import (
    _Gathered,
    _Half,
    _split,
    _whole_revolutions,
    to_dynamic,
)
from calstation.engine.periodicity.covariance import (
    CovarianceRecord,
    covariance_record,
    model_floor,
    noise_inflation,
    parameter_covariance,
    parameter_sigma,
    sigma_from_covariance,
)
from calstation.engine.periodicity.matching import MIN_MATCHES, _match, _Matcher
from calstation.engine.periodicity.problem import (
    IDX,
    _bounds,
    _free,
    _platter_samples,
    _Problem,
    _Reduced,
)
from calstation.engine.periodicity.schedule import Stage, final_cell_size, schedule
from calstation.engine.rangemodel import (
    ESTIMATED_NAMES,
    IDENTITY,
    OFFSET,
    SCALE,
    RangeModel,
    RangeModelName,
    estimated_indices,
    range_result_fields,
)
from calstation.engine.result import CalibrationResult
from calstation.engine.settings import DEFAULT_PLATTER_RADIUS, PeriodicitySettings
from calstation.engine.spinscan import SpinScan, from_recording, prepare
from calstation.errors import FineTuningError

if TYPE_CHECKING:
    from calstation.engine.scan import Scan

Progress = Callable[[str, float], None]


def periodicity_fine_tune(
    recording: Scan,
    start: Extrinsics,
    settings: PeriodicitySettings = PeriodicitySettings(),
    *,
    platter_radius: float = DEFAULT_PLATTER_RADIUS,
    progress: Progress | None = None,
    range_model: RangeModelName = "none",
    start_range: RangeModel = IDENTITY,
    incidence: bool = False,
    encoder: bool = False,
) -> CalibrationResult:
    """Periodicity fine-tuning on a spin-scan
    :class:`~calstation.engine.scan.Scan`."""
    try:
        return periodicity_fine_tune_scan(
            from_recording(recording),
            start,
            settings,
            platter_radius=platter_radius,
            progress=progress,
            range_model=range_model,
            start_range=start_range,
            incidence=incidence,
            encoder=encoder,
        )
    except FineTuningError as exc:
        raise FineTuningError(f"{recording.path}: {exc}") from None


def periodicity_fine_tune_points(
    p_L: FloatArray,
    phi: FloatArray,
    start: Extrinsics,
    settings: PeriodicitySettings = PeriodicitySettings(),
    *,
    platter_radius: float = DEFAULT_PLATTER_RADIUS,
    progress: Progress | None = None,
    stages: int | None = None,
) -> CalibrationResult:
    """Periodicity fine-tuning on the returns of one spin scan.

    ``p_L`` (N, 3) returns in frame L (metres), ``phi`` (N,) their platter angles (rad,
    unwrapped or not). ``start`` is the starting H; rx is held at 0. ``stages``: run only the
    first few stages of the schedule (a coarse alignment; None: all). Returns a
    :class:`CalibrationResult` (strategy ``"periodicity"``, cost = mean weighted squared
    point-to-plane distance in m² at the last stage).
    """
    p_L = np.asarray(p_L, dtype=np.float64)
    phi = np.asarray(phi, dtype=np.float64).reshape(-1)
    if p_L.ndim != 2 or p_L.shape[1] != 3 or p_L.shape[0] != phi.shape[0]:
        raise FineTuningError(
            f"periodicity needs (N, 3) returns and (N,) angles, got {p_L.shape} and {phi.shape}"
        )
    return periodicity_fine_tune_scan(
        prepare(p_L, phi),
        start,
        settings,
        platter_radius=platter_radius,
        progress=progress,
        stages=stages,
    )


def periodicity_fine_tune_scan(
    scan: SpinScan,
    start: Extrinsics,
    settings: PeriodicitySettings = PeriodicitySettings(),
    *,
    platter_radius: float = DEFAULT_PLATTER_RADIUS,
    progress: Progress | None = None,
    stages: int | None = None,
    warm: bool = False,
    range_model: RangeModelName = "none",
    start_range: RangeModel = IDENTITY,
    incidence: bool = False,
    encoder: bool = False,
) -> CalibrationResult:
    """Periodicity fine-tuning on a prepared :class:`~calstation.engine.spinscan.SpinScan`: as
    :func:`periodicity_fine_tune_points`, without the per-scan preparation (done as the lines
    arrived, or once for several fine-tunings).

    ``warm``: ``start`` is the result of a fine-tuning on part of this scan (the turns before
    the last): only the last stage runs, from it, with its cells sized for the whole scan (an
    update after each revolution: 0.2–1.2 s at 180–1000 lines/s on one core, within 0.007° in
    ry of a full run on the simulator).

    ``range_model``: the lidar's range terms (``calibration.range_model``; with ``incidence``
    the incidence bias too) are held at ``start_range`` and every return corrected by them; the
    result carries them without a σ, and ``diagnostics["follows"]`` says how H would follow each
    (the QA cube sets them: :func:`calstation.engine.joint.combine_range_with_cube_scan`). ty
    is held too, in the last stage, at the coarse stages' estimate (the platter's level held
    there; a ``warm`` update holds it at ``start``'s). ``encoder``: the result says how it
    follows the encoder's angle error (``diagnostics["follows_encoder"]``), for a station
    whose encoder's accuracy is stated."""
    t_start = time.perf_counter()
    timings: dict[str, float] = {f"scan_{k}": v for k, v in scan.timings.items()}
    keep = _whole_revolutions(scan)
    start6 = np.concatenate([start.with_(rx=0.0).as_vector(), start_range.as_vector()])
    halves, halves_all, p_static = _split(scan, keep, start6, platter_radius)
    noise = scan.noise
    timings["prepare"] = time.perf_counter() - t_start
    final_voxel = _final_cell(halves, noise)
    schedule_ = schedule(settings, final_voxel)[:stages]
    if warm:
        schedule_ = schedule_[-1:]
        x6 = start6.copy()
    else:
        x6 = _centred_start(halves, start6, settings, schedule_)
    # the range terms are held and the result says how it follows them
    # (``diagnostics["follows"]``), for the QA cube to set: a spin scan sees the offset only
    # through the platter's tilt against the target's axis (σ 0.35 mm at 1000 lines/s, and
    # biased by an unmodelled incidence bias at that level), cannot see a scale error (a scaled
    # world turns alike), and reads an incidence bias as an axis offset (its facets are seen at
    # ~25° from one side and ~65° from the other)
    terms: list[int] = []
    model = estimated_indices(range_model, incidence)
    run = _Run(start6, p_static, settings, platter_radius, progress, len(schedule_), noise,
               terms, level_free=bool(model))
    x6, stage_timings = _run_stages(run, schedule_, halves, halves_all, x6)
    timings.update(stage_timings)
    timings.update(run.timings)
    uncertainty = _uncertainty(run, noise)
    timings["total"] = time.perf_counter() - t_start
    if progress is not None:
        progress("periodicity done", 1.0)
    # ty too, where the coarse stages put it: the platter gives the last stage no origin, the
    # QA cube's top does
    held = ([IDX["ty"]] if model else []) + [i for i in model if i not in terms]
    return _result(x6, start6, settings, scan, run, uncertainty, final_voxel, timings,
                   model, held, encoder)


def _final_cell(halves: list[_Half], noise: float) -> float:
    """The last stage's cell size for the moving returns' two half-turns
    (:func:`final_cell_size`)."""
    return final_cell_size(
        [h.p_L for h in halves],
        [h.phi for h in halves],
        noise,
        [(h.rng, h.az) for h in halves if h.rng is not None and h.az is not None],
    )


def _centred_start(
    halves: list[_Half], start6: FloatArray, settings: PeriodicitySettings, schedule_: list[Stage]
) -> FloatArray:
    """The start of the first stage: the stage-0 centroid alignment (:func:`_centre_halves`)
    when the schedule is coarse-to-fine and it gives the first stage more matches, else
    ``start6``."""
    x6 = start6.copy()
    if settings.coarse_to_fine:
        # keep the centroid alignment only where it helps: the view asymmetry of the two
        # half-turns biases the centroids, so a good start can be better than its result
        centred = _centre_halves(halves, x6, settings, np.random.default_rng(1))
        first = schedule_[0]
        cells = [h.cells(first.voxel) for h in halves]
        if _match(cells, centred, first)[0].pa.shape[0] > _match(cells, x6, first)[0].pa.shape[0]:
            x6 = centred
    return x6


def _run_stages(
    run: _Run,
    schedule_: list[Stage],
    halves: list[_Half],
    halves_all: list[_Gathered],
    x6: FloatArray,
) -> tuple[FloatArray, dict[str, float]]:
    """Every stage of ``schedule_`` from ``x6``, each on its own cells: of the moving returns
    while ry is held, of all returns after. Returns the final H (as a vector) and the seconds
    per stage.

    A stage that loses the platter or its matches is run again from where the previous stage
    started (noted in ``run.restarts``): a coarse stage with ry held can walk away from a good
    start (on a simulated 4-turn scan, the 20 mm stage walked tx 16 mm away from a start 1 mm
    and 0.5° in ry off, and the next stage lost the platter). The abandoned attempt's outer
    iterations stay in the history.
    """
    rng = np.random.default_rng(0)
    timings: dict[str, float] = {}
    before = x6.copy()  # the H the previous stage started from
    for s_i, stage in enumerate(schedule_):
        t_stage = time.perf_counter()
        source: list[_Half] | list[_Gathered] = halves if stage.hold_ry else halves_all
        # one half-turn gathered at a time: only its cells are kept
        stage_halves = [h.subset(stage.max_points, rng).cells(stage.voxel) for h in source]
        run.timings["cells"] += time.perf_counter() - t_stage
        start_of_stage = x6.copy()
        try:
            x6 = run.stage(s_i, stage, _Matcher(stage_halves, stage), x6)
        except FineTuningError:
            if s_i == 0 or np.array_equal(before, start_of_stage):
                raise
            run.restarts.append(s_i + 1)
            x6 = run.stage(s_i, stage, _Matcher(stage_halves, stage), before.copy())
        before = start_of_stage
        timings[f"stage{s_i + 1}"] = time.perf_counter() - t_stage
    return x6, timings


class Iteration(TypedDict):
    """One outer iteration of a stage, as ``diagnostics["iterations"]`` keeps it: the stage
    (from 1), its cell size (m), the points and matches, the platter samples, the mean squared
    residual and the function evaluations."""

    stage: int
    voxel_m: float
    points: int
    matches: int
    platter_samples: int
    cost: float
    nfev: int

@dataclass(frozen=True)
class _Uncertainty:
    """σ of the final estimate and how it was obtained (metres / radians, SI)."""

    sigma: dict[str, float]
    """reported: the cluster-robust σ times :func:`noise_inflation` (:data:`SIGMA_SCALE`)"""
    independent: dict[str, float]
    """σ²·(JᵀJ)⁻¹ with independent residuals"""
    blocks: dict[str, float]
    """cluster-robust over spatial blocks of :data:`SIGMA_BLOCK`"""
    inflation: float
    """:func:`noise_inflation` of the scan's range noise (a constant for a noisy scan)"""
    covariance: CovarianceRecord | None
    """the reported covariance as stored (:func:`covariance_record`)"""


def _uncertainty(run: _Run, noise: float) -> _Uncertainty:
    """The covariance at the last inner solution of ``run``, scaled by
    :func:`noise_inflation` of the range ``noise``."""
    assert run.last is not None
    x_last, problem = run.last
    res = problem.solution(x_last)
    sigma_independent = parameter_sigma(res, problem.free)
    covariance = parameter_covariance(res, problem.free, blocks=problem.row_blocks())
    sigma_blocks = sigma_from_covariance(covariance, problem.free)
    inflation = noise_inflation(noise)
    sigma = {k: v * inflation for k, v in sigma_blocks.items()}
    reported_cov = None
    if covariance is not None:
        reported_cov = covariance * inflation**2 + model_floor(problem.free)
        sigma = sigma_from_covariance(reported_cov, problem.free)
    return _Uncertainty(
        sigma,
        sigma_independent,
        sigma_blocks,
        inflation,
        covariance_record(reported_cov, problem.free),
    )


def _result(
    x6: FloatArray,
    start6: FloatArray,
    settings: PeriodicitySettings,
    scan: SpinScan,
    run: _Run,
    uncertainty: _Uncertainty,
    final_voxel: float,
    timings: dict[str, float],
    terms: list[int] | None = None,
    held: list[int] | None = None,
    encoder: bool = False,
) -> CalibrationResult:
    """The :class:`CalibrationResult` of the run, with its diagnostics; ``terms`` the range
    terms of the recipe's model, ``held`` those of them held (their start, with no σ; how the
    estimate follows them in ``diagnostics["follows"]``)."""
    ry_lo = start6[4] - math.radians(settings.ry_bound_deg)
    ry_hi = start6[4] + math.radians(settings.ry_bound_deg)
    at_bound = min(abs(x6[4] - ry_lo), abs(x6[4] - ry_hi)) < math.radians(0.01)
    sigma = dict(uncertainty.sigma)
    terms = list(terms or [])
    ranges = range_result_fields(x6, sigma, terms)
    return CalibrationResult(
        H=Extrinsics.from_vector(x6[:6]),
        sigma=sigma,
        cost=run.cost,
        iterations=run.outer,
        strategy="periodicity",
        timings=timings,
        diagnostics={
            "gauge": settings.gauge,
            "gauge_note": (
                "origin along the axis fixed by the platter top plane x_P = 0"
                if settings.gauge == "platter"
                else "ty held at its start value (paper §IV-C)"
            ),
            "coarse_to_fine": settings.coarse_to_fine,
            "matches_per_iteration": [h["matches"] for h in run.history],
            "stages_restarted": run.restarts,
            "iterations": run.history,
            "static_returns": int(scan.static.sum()),
            "range_noise_m": scan.noise,
            "sigma_independent": uncertainty.independent,
            "sigma_blocks": uncertainty.blocks,
            "sigma_noise_inflation": uncertainty.inflation,
            "covariance": uncertainty.covariance,
            "final_cell_m": final_voxel,
            "moving_returns": int((~scan.static).sum()),
            "ry_at_bound": bool(at_bound),
            "ry_bound_rad": [ry_lo, ry_hi],
            "rms_m": math.sqrt(run.cost),
            **({"follows_encoder": _follows_encoder(run)} if encoder else {}),
            **({"range_model": [ESTIMATED_NAMES[i] for i in terms],
                "follows": _follows(run, x6, held or [])} if terms else {}),
        },
    ).with_range(ranges)


def _follows_encoder(run: _Run) -> dict[str, dict[str, float]]:
    """How the estimate follows the encoder's angle error, per radian of each of its
    coefficients (:meth:`~calstation.engine.periodicity.problem._Problem.encoder_follows`):
    the spin target's share of what the combination with the QA cube carries
    (:mod:`calstation.engine.encoder`)."""
    if run.last is None:
        return {}
    x_last, problem = run.last
    return problem.encoder_follows(x_last)


def _follows(run: _Run, x: FloatArray, held: list[int]) -> dict[str, dict[str, float]]:
    """How the estimate follows each ``held`` range term, per unit of it. The scale error,
    which a spin scan cannot see, exactly: a world scaled by (1 + ε) turns alike with the
    translation scaled by (1 + ε), the offset and the rotations unchanged, and the scale error
    k ← k − ε; so ∂t/∂k = −t. The others from the last stage's least-squares response
    (:meth:`~calstation.engine.periodicity.problem._Problem.follows`)."""
    out: dict[str, dict[str, float]] = {}
    others = [i for i in held if i != SCALE]
    if others and run.last is not None:
        x_last, problem = run.last
        out.update(problem.follows(x_last, others))
    if SCALE in held:
        # the scaled world moves ty too, which is held: what the estimate does when ty moves
        # with it is taken back out (∂/∂k at ty held = −t + ∂/∂ty·ty)
        by_ty = out.get("ty", {})
        out["range_scale"] = {
            name: (-float(x[i]) if i < 3 else 0.0) + by_ty.get(name, 0.0) * float(x[1])
            for i, name in enumerate(("tx", "ty", "tz", "rx", "ry", "rz"))
            if name in by_ty or i in (0, 2)
        }
    return out


class _Run:
    """The outer iterations of the stages: matching, solving, and what they leave behind."""

    def __init__(
        self,
        start6: FloatArray,
        p_static: FloatArray,
        settings: PeriodicitySettings,
        platter_radius: float,
        progress: Progress | None,
        n_stages: int,
        noise: float = math.nan,
        range_terms: list[int] | None = None,
        level_free: bool = False,
    ) -> None:
        self.range_terms = list(range_terms or [])
        """the range terms the last stage frees (indices after H's)"""
        self.level_free = level_free
        """in the last stage, ty held and the platter's level free (:class:`_Problem`'s
        ``platter_level_free``); the coarse stages hold the level and estimate ty"""
        self.noise = noise
        """range noise σ (m) measured on the scan (NaN: unknown)"""
        self.start6 = start6
        self.p_static = p_static
        self.settings = settings
        self.platter_radius = platter_radius
        self.progress = progress
        self.n_stages = n_stages
        self.history: list[Iteration] = []
        self.last: tuple[FloatArray, _Problem] | None = None
        """the last inner solution and its problem"""
        self.outer = 0
        self.cost = math.nan
        self.restarts: list[int] = []
        """the stages (from 1) run again from where the previous stage started"""
        self.timings = {"cells": 0.0, "match": 0.0, "solve": 0.0}

    def stage(self, s_i: int, stage: Stage, match: _Matcher, x6: FloatArray) -> FloatArray:
        """Iterate one stage from ``x6``; returns the H (as a vector) it ends on."""
        settings = self.settings
        level_free = self.level_free and not stage.hold_ry
        # with the lidar's range model the platter gives the last stage the axis's direction,
        # not its origin: ty is held there, where the coarse stages put it (set with the range
        # model by the QA cube's top). The coarse stages hold the platter's level and estimate
        # ty, as without the model: with ty held at the start and the level free, the 10 mm
        # stage swung H along the axis by up to 20 mm an iteration and lost the platter
        gauge_ty = settings.gauge == "ty" or not stage.use_platter or level_free
        # the range offset, as weakly seen as ry, is freed with it in the last stage
        terms = [] if stage.hold_ry else self.range_terms
        free = [i for i in _free(gauge_ty, terms) if not (stage.hold_ry and i == IDX["ry"])]
        for outer in range(stage.max_outer):
            if self.progress is not None:
                self.progress(
                    f"periodicity stage {s_i + 1}/{self.n_stages} ({stage.voxel * 1e3:.0f} mm)",
                    (s_i + outer / stage.max_outer) / self.n_stages,
                )
            t0 = time.perf_counter()
            matched, n_pts = match(x6)
            platter = self._platter(stage, x6)
            t1 = time.perf_counter()
            n_matches = matched.pa.shape[0]
            if n_matches < MIN_MATCHES:
                raise FineTuningError(
                    f"periodicity stage {s_i + 1}: only {n_matches} matches between the two "
                    f"half-turns (voxel {stage.voxel * 1e3:.0f} mm, radius "
                    f"{stage.match_radius * 1e3:.0f} mm); the start is too far off or the spin "
                    "target is not seen in both half-turns"
                )
            problem = _Problem(matched, platter, 1.0, free, x6, self.noise, level_free)
            lo, hi = _bounds(x6, self.start6, free, settings)
            reduced = _Reduced(problem, x6[free])
            res = least_squares(
                reduced.residuals,
                x6[free],
                jac=reduced.jacobian,
                bounds=(lo, hi),
                method="trf",
                x_scale=np.full(len(free), 1e-3),
                xtol=settings.xtol,
                ftol=settings.ftol,
                max_nfev=settings.max_nfev,
            )
            self.timings["match"] += t1 - t0
            self.timings["solve"] += time.perf_counter() - t1
            new6 = problem.full(res.x)
            step = np.abs(new6 - x6)
            x6 = new6
            self.outer += 1
            self.cost = float(np.mean(reduced.full_residuals(res.x) ** 2))
            self.last = (res.x, problem)
            self.history.append(
                Iteration(
                    stage=s_i + 1,
                    voxel_m=stage.voxel,
                    points=n_pts,
                    matches=int(n_matches),
                    platter_samples=0 if platter is None else int(platter.shape[0]),
                    cost=self.cost,
                    nfev=int(res.nfev),
                )
            )
            if _converged(self.history, outer, step, stage):
                break
        return x6

    def _platter(self, stage: Stage, x6: FloatArray) -> FloatArray | None:
        if not stage.use_platter:
            return None
        # wide enough for the range noise: a band that cut into it would select the returns by
        # their noise, and by how much of it their ray's angle turns into height
        noise = self.noise if math.isfinite(self.noise) else 0.0
        tolerance = max(0.003, stage.voxel, 3.0 * noise)
        platter = _platter_samples(self.p_static, x6, tolerance, self.platter_radius)
        if platter.shape[0] < 20:
            raise FineTuningError(
                "gauge 'platter': the platter top is not visible in the spin scan "
                f"({platter.shape[0]} static returns near x_P = 0 under the current estimate); "
                "the start may be too far off (run the coarse stages, or start from the initial "
                "calibration), or the platter is hidden (use gauge: ty)"
            )
        return platter


def _converged(history: list[Iteration], outer: int, step: FloatArray, stage: Stage) -> bool:
    """Stop the outer loop of a stage?

    While ry is held, a stalled cost or a step below the cell's resolution ends the stage. Once
    ry is free the cost is nearly flat in it, so only the parameter step counts: a cost-based
    stop ended the loop while ry was still walking back from a wrong start.
    """
    small_step = (
        step[:3].max() < stage.voxel * 0.02
        and step[5] < math.radians(0.001) * stage.voxel / 0.002
        and step[4] < math.radians(0.002)
        and (step.size <= OFFSET or step[OFFSET] < stage.voxel * 0.02)
    )
    if not stage.hold_ry:
        return bool(small_step)
    prev_cost = history[-2]["cost"] if len(history) > 1 and outer > 0 else math.inf
    cost = history[-1]["cost"]
    return bool(small_step or (outer > 0 and abs(prev_cost - cost) <= 1e-3 * cost))


def _centre_halves(
    halves: list[_Half], x6: FloatArray, settings: PeriodicitySettings, rng: np.random.Generator
) -> FloatArray:
    """Stage 0 (calstation): move tx and tz so that the centroids of the two half-turn
    reconstructions coincide. Smooth, with a basin as wide as the target, it brings starts
    200 mm off within reach of the first matching stage. ty (gauge), ry and rz stay. The caller
    keeps the result only if it gives more first-stage matches than the start."""
    sub = [h.subset(20_000, rng) for h in halves]
    cs = [(np.cos(h.phi), np.sin(h.phi)) for h in sub]
    free = [IDX["tx"], IDX["tz"]]

    def fun(x: FloatArray) -> FloatArray:
        v = x6.copy()
        v[free] = x
        a = to_dynamic(sub[0].p_L, *cs[0], v)
        b = to_dynamic(sub[1].p_L, *cs[1], v)
        return np.asarray(a.mean(axis=0) - b.mean(axis=0), dtype=np.float64)

    half = 2.0 * settings.translation_bound * 5
    x0 = x6[free]
    res = least_squares(fun, x0, bounds=(x0 - half, x0 + half), method="trf", max_nfev=30)
    out = x6.copy()
    out[free] = res.x
    return out
