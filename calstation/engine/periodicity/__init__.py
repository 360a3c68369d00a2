"""Periodicity-constrained fine-tuning (paper §III-B-2, §IV-C; DESIGN §5) with calstation's
robustness additions.

Every surface point of the spin target is seen twice per revolution: once in the half-turn
φ ∈ [0, π) and once in [π, 2π). With the right H both half-turn reconstructions in frame D
coincide. The cost is the weighted point-to-plane distance between mutual nearest neighbours of
the two halves, ``Σ w·(n·(x − x′))²`` with normals from the nearest points and the planarity
weight ``w = 2(λ2 − λ3)/(λ1 + λ2 + λ3)``, minimised by SciPy's TRF.

What calstation adds (docs/algorithms.md):

- **Static-point removal.** Returns that stay at the same place in L over the whole scan (the
  platter ring, the background, any face of revolution) carry no periodicity information; they
  are found per azimuth bin, independently of H, and dropped. Points within a few mm of the
  platter top are dropped too once H is good enough to tell them apart.
- **Coarse-to-fine schedule.** A centroid alignment of the two half-turns (stage 0), then four
  matching stages whose cell size, match radius and normal neighbourhood shrink (20 → 1 mm), so
  matching converges from starts 100–200 mm and 1–2° off. Cells are cut on the sensor grid
  (platter angle × azimuth) and average the raw returns (in L) with their platter angles:
  unbiased by the range noise, and computed once per stage.
- **Point-to-local-plane residuals, symmetric.** Each match contributes the distance of each end
  to the plane fitted around the other end.
- **Bounds.** tx, ty, tz and rz are bounded ±``translation_bound``/±``rotation_bound_deg``
  around the current estimate (re-centred every outer iteration: they are sharp in the cost);
  ry is bounded ±``ry_bound_deg`` around its *start* and never re-centred (the cost is nearly
  flat in ry; a re-centred bound lets it walk away).
- **Gauge.** The periodicity cost cannot see a shift along the axis. ``gauge: platter`` (the
  default) fixes it with the platter: the top surface of the platter is the plane x_P = 0, so
  the static platter returns add the residual x_P = a·(p_L − t) = 0, which also sharpens rz. The
  coarse stages hold ty fixed (the paper's fix) until the platter is identified.
  ``gauge: ty`` is the paper's fix throughout.
- **Covariance** σ²·(JᵀJ)⁻¹ from the final Jacobian with σ² from the residuals, matches per
  iteration, per-stage costs and timings in the diagnostics.

The package, from the bottom up: :mod:`.cells` (the two half-turns, subsets, sensor-grid
cells), :mod:`.schedule` (the stages, the last stage's cell size), :mod:`.covariance` (σ and
covariance, noise inflation), :mod:`.problem` (residuals, Jacobian, reduced problem, bounds),
:mod:`.matching` (the half-turns' matches under an H) and :mod:`.solve` (the stages run, the
public entry points). Everything public is importable from ``calstation.engine.periodicity``.
"""

from __future__ import annotations

from calstation.engine.periodicity.cells import (
    sensor_cells as sensor_cells,
    static_samples as static_samples,
    to_dynamic as to_dynamic,
)
from calstation.engine.periodicity.covariance import (
    MODEL_FLOOR_DEG as MODEL_FLOOR_DEG,
    SIGMA_BLOCK as SIGMA_BLOCK,
    SIGMA_SCALE as SIGMA_SCALE,
    block_ids as block_ids,
    covariance_record as covariance_record,
    noise_inflation as noise_inflation,
    parameter_covariance as parameter_covariance,
    parameter_sigma as parameter_sigma,
    sigma_from_covariance as sigma_from_covariance,
)
from calstation.engine.periodicity.matching import MIN_MATCHES as MIN_MATCHES
from calstation.engine.periodicity.problem import IDX as IDX
from calstation.engine.periodicity.schedule import (
    CELL_NOISE_RATIO as CELL_NOISE_RATIO,
    CELL_SIZES as CELL_SIZES,
    FINAL_MAX_OUTER as FINAL_MAX_OUTER,
    Stage as Stage,
    final_cell_size as final_cell_size,
    schedule as schedule,
)
from calstation.engine.periodicity.solve import (
    Progress as Progress,
    periodicity_fine_tune as periodicity_fine_tune,
    periodicity_fine_tune_points as periodicity_fine_tune_points,
    periodicity_fine_tune_scan as periodicity_fine_tune_scan,
)
from calstation.engine.spinscan import (
    static_mask as static_mask,  # re-exported: shape and the bench use it
)
