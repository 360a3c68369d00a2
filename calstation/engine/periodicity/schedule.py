"""The coarse-to-fine schedule of the periodicity fine-tuning: its stages and the cell size of
the last one, chosen from the scan's range noise and density."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from calstation.engine.frames import FloatArray, lidar_to_polar
from calstation.engine.periodicity.cells import _cell_counts
from calstation.engine.settings import PeriodicitySettings


@dataclass(frozen=True)
class Stage:
    """One step of the coarse-to-fine schedule (metres)."""

    voxel: float
    match_radius: float
    normal_neighbours: int
    platter_drop: float | None
    """drop points with x_P below this (None: only static points are dropped)"""
    use_platter: bool
    """add the platter residual (gauge ``platter``) in this stage"""
    max_points: int | None
    """random subset of raw returns per half-turn used in this stage (None: all)"""
    max_outer: int
    """outer iterations (re-matching) at most"""
    hold_ry: bool = False
    """keep ry at its current value (coarse cells cannot resolve it and let it wander)"""
    one_sided: bool = False
    """match every cell to the plane around its nearest cell in the other half-turn, without
    the mutual test (:meth:`calstation.engine.periodicity.matching._Matcher._one_sided`)"""


def schedule(settings: PeriodicitySettings, final_voxel: float = 0.001) -> list[Stage]:
    """The stages for ``settings``: four coarse-to-fine stages, or the paper's single stage.

    ``final_voxel`` (m) is the cell size of the last stage, chosen from the scan's noise and
    density by :func:`final_cell_size`. ry is held in every stage but the last: coarse cells
    and the few hundred matches of the 5 mm stage cannot resolve it and throw it to its bound.
    The last stage matches one-sided: the mutual test selects pairs on their noise, which the
    covariance does not see (docs/algorithms.md).
    """
    k = settings.normal_neighbours
    platter = settings.gauge == "platter"
    if not settings.coarse_to_fine:
        return [
            Stage(
                final_voxel,
                max(settings.match_distance, 4 * final_voxel),
                max(8, k // 2),
                0.004,
                platter,
                None,
                settings.max_outer,
            )
        ]
    n = settings.max_outer
    fine = max(final_voxel, 0.001)
    return [
        Stage(
            0.020, min(0.12, settings.match_distance), max(8, k // 4), None, False, 60_000, n, True
        ),
        Stage(
            0.010,
            min(0.05, settings.match_distance),
            max(12, k // 3),
            0.008,
            platter,
            120_000,
            n,
            True,
        ),
        Stage(
            max(0.005, fine),
            min(0.02, settings.match_distance),
            max(16, k // 2),
            0.005,
            platter,
            300_000,
            n,
            True,
        ),
        Stage(
            fine,
            min(4 * fine, settings.match_distance),
            max(8, k // 2),
            0.004,
            platter,
            None,
            max(n, FINAL_MAX_OUTER),
            one_sided=True,
        ),
    ]


FINAL_MAX_OUTER = 30
"""Outer iterations allowed in the last stage: it stops on the parameter step, not the cost."""

CELL_SIZES = (0.001, 0.0015, 0.002, 0.0025, 0.003, 0.004, 0.005)
"""Candidate cell sizes of the last stage (m), smallest first."""

CELL_NOISE_RATIO = 1.0 / 3.0
"""The last stage's cells must average the range noise down to this fraction of their size."""


def final_cell_size(
    halves_p_L: list[FloatArray],
    halves_phi: list[FloatArray],
    noise: float,
    halves_polar: list[tuple[FloatArray, FloatArray]] | None = None,
) -> float:
    """The smallest cell size of :data:`CELL_SIZES` whose cells average the range noise down to
    :data:`CELL_NOISE_RATIO` of their size (m).

    Mutual nearest neighbours between the two half-turns prefer pairs whose noise cancels their
    misalignment; when a cell's noise (σ/√returns) is comparable to the cell spacing, each outer
    iteration recovers only a few per cent of an ry error, and ry stays biased (docs/algorithms.md).
    The count per cell is the median over the target's cells of both halves. ``halves_polar``:
    the (range, azimuth) of each half's returns, when already known.
    """
    if not math.isfinite(noise) or noise <= 0:
        return CELL_SIZES[0]
    polar = halves_polar or [lidar_to_polar(p) for p in halves_p_L]
    for size in CELL_SIZES:
        counts = np.concatenate(
            [
                _cell_counts(r, a, ph, size)
                for (r, a), ph in zip(polar, halves_phi, strict=True)
                if ph.size
            ]
            or [np.zeros(0, dtype=np.int64)]
        )
        per_cell = float(np.median(counts)) if counts.size else 1.0
        if noise / math.sqrt(per_cell) <= CELL_NOISE_RATIO * size:
            return size
    return CELL_SIZES[-1]
