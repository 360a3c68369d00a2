"""Cost landscapes (paper Fig. 9): each fine-tuning cost sampled on a grid of two parameters
around the value that method converged to from the initial calibration, for one scenario.

The grid is split into rows, one task per row, so the workers share the sampling. The costs come
from the engine's own public cost-evaluation functions (see :func:`cost_evaluator`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Protocol

import numpy as np

from calstation.bench import BenchError
from calstation.bench.records import BenchRecord
from calstation.bench.tasks import BenchConfig, Task, scenario_dir
from calstation.engine.frames import PARAMETER_NAMES, Extrinsics

if TYPE_CHECKING:
    from calstation.recipes import Recipe
    from calstation.recordings.recorded import Recording

class _Recorded(Protocol):
    """The records finished so far, by task id (the bench's record store)."""

    @property
    def records(self) -> Mapping[str, BenchRecord]: ...


Cost = tuple[Callable[[Extrinsics], float], str]
"""A function H → scalar cost, and the engine functions behind it."""

PAIRS: dict[str, tuple[str, str]] = {"translation": ("tx", "tz"), "rotation": ("ry", "rz")}
"""The two landscapes: over two translations (ty is the gauge/fixed one) and over ry × rz."""


def landscape_tasks(config: BenchConfig, store: _Recorded) -> list[Task]:
    """One task per (method, pair, grid row) for ``config.landscape_scenario``, centred on each
    method's result from the initial calibration (skipped if that run failed)."""
    scen = next((s for s in config.scenarios if s.name == config.landscape_scenario), None)
    if scen is None:
        return []
    n = int(config.landscape_grid)
    tasks = []
    for method in config.methods:
        rec = store.records.get(f"{scen.name}/{method}/init/000")
        if rec is None or rec.get("status") != "ok":
            continue
        centre = [float(rec["H"][p]) for p in PARAMETER_NAMES]
        truth = [float(rec["truth"][p]) for p in PARAMETER_NAMES]
        for pair_name, pair in PAIRS.items():
            half = (
                config.landscape_translation_m
                if pair_name == "translation"
                else math.radians(config.landscape_rotation_deg)
            )
            offsets = np.linspace(-half, half, n).tolist()
            for row in range(n):
                tasks.append(
                    Task(
                        f"{scen.name}/landscape/{method}/{pair_name}/{row:03d}",
                        "landscape",
                        scen.name,
                        str(scenario_dir(config, scen)),
                        method=method,
                        landscape={
                            "method": method,
                            "pair_name": pair_name,
                            "pair": list(pair),
                            "row": row,
                            "offsets": offsets,
                            "centre": centre,
                            "truth": truth,
                        },
                    )
                )
    return tasks


def _display(param: str, value: float) -> float:
    """SI → display units (mm, °)."""
    return value * 1e3 if param.startswith("t") else math.degrees(value)


def run_landscape_row(
    task: Task, recording: Callable[[str, str], Recording], recipe: Recipe
) -> BenchRecord:
    """Evaluate one grid row: the first parameter of the pair fixed at ``offsets[row]``, the
    second swept over ``offsets``. Returns ``{"landscape": {...}}`` with the costs (None where
    the cost could not be evaluated) and the axes in display units."""
    spec = task.landscape
    method, (p, q) = spec["method"], spec["pair"]
    centre = Extrinsics(*spec["centre"])
    truth = Extrinsics(*spec["truth"])
    from calstation import plugins

    strategy = plugins.strategy(method)
    fixture = getattr(strategy, "fixture", "spin_target")
    rec = recording(task.directory, "cube" if fixture == "qa_cube" else "spin")
    cost, source = cost_evaluator(method, rec, recipe, centre)
    offsets = spec["offsets"]
    costs: list[float | None] = []
    t0 = time.perf_counter()
    base = centre.as_vector()
    ip, iq = PARAMETER_NAMES.index(p), PARAMETER_NAMES.index(q)
    for dv in offsets:
        v = base.copy()
        v[ip] += offsets[spec["row"]]
        v[iq] += dv
        try:
            c = float(cost(Extrinsics.from_vector(v)))
            costs.append(c if math.isfinite(c) else None)
        except Exception:
            costs.append(None)
    return {
        "landscape": {
            "method": method,
            "pair_name": spec["pair_name"],
            "pair": [p, q],
            "row": spec["row"],
            "u": [_display(p, o) for o in offsets],
            "v": [_display(q, o) for o in offsets],
            "costs": costs,
            "truth": [
                _display(p, getattr(truth, p) - getattr(centre, p)),
                _display(q, getattr(truth, q) - getattr(centre, q)),
            ],
            "source": source,
        },
        "stage_s": time.perf_counter() - t0,
    }


_PREPARED: dict[tuple[str, str], Cost] = {}
"""Per worker: the prepared cost of (recording path, method), reused by every row."""


def cost_evaluator(
    method: str, recording: Recording, recipe: Recipe, centre: Extrinsics
) -> Cost:
    """A function H → scalar cost of ``method`` on ``recording``, and a description of the
    engine functions behind it. Prepared once per worker and recording, then reused."""
    key = (str(recording.path), method)
    if key not in _PREPARED:
        if len(_PREPARED) > 4:
            _PREPARED.clear()
        if method == "periodicity":
            _PREPARED[key] = _periodicity_cost(recording, recipe, centre)
        elif method == "shape":
            _PREPARED[key] = _shape_cost(recording, recipe, centre)
        else:
            raise BenchError(f"no cost landscape for strategy {method!r}")
    return _PREPARED[key]


LANDSCAPE_CELL_M = 0.005
"""Sensor-grid cell size (m) for the periodicity landscape: the engine's third stage."""


def _periodicity_cost(
    recording: Recording, recipe: Recipe, centre: Extrinsics
) -> Cost:
    """The paper's periodicity cost, re-matched at every H (as the optimiser's outer loop sees
    it), built from the public helpers of :mod:`calstation.engine.periodicity`.

    calstation.engine.periodicity exposes no public whole-cost function, so: static returns
    dropped (``static_mask``), both half-turns averaged over ``sensor_cells`` of 5 mm
    (independent of H), mapped to D (``to_dynamic``), platter points (x_P ≤ 5 mm) dropped,
    ``mutual_neighbours`` within the recipe's ``match_distance`` (paper: 20 cm), planes from
    ``weighted_normals``; cost = mean over matches of w·(n·(x − x′))², both ends' planes. The
    platter gauge residual is not included (it is calstation's gauge, not the paper's cost).
    """
    from calstation.engine.neighbours import mutual_neighbours, weighted_normals
    from calstation.engine.periodicity import sensor_cells, to_dynamic
    from calstation.engine.spinscan import static_mask

    settings = recipe.calibration.periodicity
    p_L, phi = recording.points_lidar()
    phi = np.asarray(phi, dtype=np.float64)
    keep = phi < np.nanmin(phi) + 2 * math.pi
    p_L, phi = p_L[keep], phi[keep]
    dyn = ~static_mask(p_L)
    p_L, phi = p_L[dyn], np.mod(phi[dyn], 2 * math.pi)
    c6 = centre.as_vector()
    q0 = to_dynamic(p_L, np.ones(len(phi)), np.zeros(len(phi)), c6)
    radius = recipe.fixtures.platter.radius
    roi = (q0[:, 0] > -0.2) & (q0[:, 0] < 0.6) & (np.hypot(q0[:, 1], q0[:, 2]) < radius + 0.25)
    halves = []
    for sel in (phi < math.pi, phi >= math.pi):
        cells, ph = sensor_cells(p_L[sel & roi], phi[sel & roi], LANDSCAPE_CELL_M)
        halves.append((cells, np.cos(ph), np.sin(ph)))
    k = max(8, int(settings.normal_neighbours) // 2)
    match_radius = float(settings.match_distance)

    def cost(H: Extrinsics) -> float:
        x6 = H.as_vector()
        d = []
        for cells, c, s in halves:
            pts = to_dynamic(cells, c, s, x6)
            d.append(pts[pts[:, 0] > 0.005])
        i, j = mutual_neighbours(d[0], d[1], match_radius)
        if i.size < 50:
            return math.nan
        na, wa, ma = weighted_normals(d[0], k, i)
        nb, wb, mb = weighted_normals(d[1], k, j)
        ra = wa * np.einsum("ij,ij->i", na, ma - d[1][j]) ** 2
        rb = wb * np.einsum("ij,ij->i", nb, mb - d[0][i]) ** 2
        return float(np.mean(np.concatenate([ra, rb])))

    return cost, (
        "calstation.engine.periodicity public helpers (static_mask, sensor_cells 5 mm, to_dynamic, "
        "mutual_neighbours, weighted_normals); re-matched at every H"
    )


def _shape_cost(
    recording: Recording, recipe: Recipe, centre: Extrinsics
) -> Cost:
    """The shape-constrained cost C1 + C2 of :class:`calstation.engine.shape.ShapeCost` (the
    engine's
    public cost object), on the returns the strategy itself would use: moving returns
    (``static_mask``) near the cube under the centre H, a fixed subset of 20 000, the box kind
    the recipe selects (``calibration.options.shape.box``, default upright)."""
    from calstation.engine.frames import lidar_to_dynamic
    from calstation.engine.geometry import segment_above_platter
    from calstation.engine.shape import ShapeCost
    from calstation.engine.spinscan import static_mask

    cube = recipe.fixtures.qa_cube
    radius = recipe.fixtures.platter.radius
    box = str(dict(recipe.calibration.options.get("shape", {})).get("box", "upright"))
    p_L, phi = recording.points_lidar()
    moving = ~static_mask(p_L)
    p_L, phi = p_L[moving], phi[moving]
    near = segment_above_platter(
        lidar_to_dynamic(p_L, phi, centre), margin=0.0, radius=radius + 0.05,
        height=3.0 * cube.edge + 0.05,
    )
    p_L, phi = p_L[near], phi[near]
    n_all, max_points = p_L.shape[0], 20_000
    if n_all > max_points:
        pick = np.sort(np.random.default_rng(0).choice(n_all, max_points, replace=False))
        p_L, phi = p_L[pick], phi[pick]
    shape_cost = ShapeCost(
        p_L, phi, cube, recipe.calibration.shape, platter_radius=radius,
        density_scale=math.sqrt(n_all / max(1, p_L.shape[0])), box=box,
    )

    def cost(H: Extrinsics) -> float:
        r = shape_cost.residuals_of(H)
        return float(np.sum(r**2))

    return cost, f"calstation.engine.shape.ShapeCost ({box} box), C1 + C2 on the strategy's returns"
