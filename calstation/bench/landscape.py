"""Cost landscapes (paper Fig. 9): each fine-tuning cost sampled on a grid of two parameters
around the value that method converged to from the initial calibration, for one scenario.

The grid is split into rows, one task per row, so the workers share the sampling. The costs come
from the engine's own public cost-evaluation functions (see :func:`cost_evaluator`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from ..frames import PARAMETER_NAMES, Extrinsics
from . import BenchError

PAIRS: dict[str, tuple[str, str]] = {"translation": ("tx", "tz"), "rotation": ("ry", "rz")}
"""The two landscapes: over two translations (ty is the gauge/fixed one) and over ry × rz."""


def landscape_tasks(config: Any, store: Any) -> list[Any]:
    """One task per (method, pair, grid row) for ``config.landscape_scenario``, centred on each
    method's result from the initial calibration (skipped if that run failed)."""
    from .runner import Task, scenario_dir

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
    task: Any, recording: Callable[[str, str], Any], recipe: Any
) -> dict[str, Any]:
    """Evaluate one grid row: the first parameter of the pair fixed at ``offsets[row]``, the
    second swept over ``offsets``. Returns ``{"landscape": {...}}`` with the costs (None where
    the cost could not be evaluated) and the axes in display units."""
    spec = task.landscape
    method, (p, q) = spec["method"], spec["pair"]
    centre = Extrinsics(*spec["centre"])
    truth = Extrinsics(*spec["truth"])
    from .. import plugins

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


def cost_evaluator(
    method: str, recording: Any, recipe: Any, centre: Extrinsics
) -> tuple[Callable[[Extrinsics], float], str]:
    """A function H → scalar cost of ``method`` on ``recording``, and the name of the engine
    function behind it. Prepared once per row (matching structures are reused where the engine
    allows)."""
    raise BenchError(f"no public cost-evaluation function found for strategy {method!r}")
