"""The worker side of the paper bench: one :class:`~calstation.bench.tasks.Task` run in a worker
process, and what the worker keeps between tasks.

Workers (separate processes, ``spawn``) load the recipe and the plugins once
(:func:`_init_worker`) and a scenario's recordings once, each spin scan's returns prepared once
too (:func:`_prepared`), keeping them while tasks of the same scenario arrive (tasks are ordered
by scenario), so no big array is pickled per task and no fine-tuning prepares its scan again.
"""

from __future__ import annotations

import json
import os
import time
import traceback
import warnings
from pathlib import Path
from typing import Any

from calstation.bench import BenchError
from calstation.bench.landscape import run_landscape_row
from calstation.bench.records import (
    _h_dict,
    _jsonable,
    against_truth,
    converged,
    result_fields,
    scan_of,
)
from calstation.bench.scenarios import load_truth, paper_scenarios, simulate_scenario
from calstation.bench.tasks import Task
from calstation.engine.frames import Extrinsics
from calstation.plugins.cost_strategies import strategy_result

_WORKER: dict[str, Any] = {}


def _init_worker(recipe_path: str) -> None:
    """Load the recipe and the plugins once per worker process."""
    warnings.simplefilter("ignore")
    os.environ.setdefault("MPLBACKEND", "Agg")
    from calstation import plugins
    from calstation.recipes import load_recipe

    _WORKER.clear()
    _WORKER["recipe_path"] = Path(recipe_path)
    _WORKER["loaded"] = load_recipe(recipe_path)
    _WORKER["cache_dir"] = None
    _WORKER["cache"] = {}
    plugins.load_plugins()


def _recording(directory: str, which: str) -> Any:
    """The scenario's ``which`` recording ("static" | "spin" | "cube"), read once per worker and
    kept until a task of another scenario arrives."""
    from calstation.recordings.reader import read_recording

    if _WORKER["cache_dir"] != directory:
        _WORKER["cache"] = {}
        _WORKER["cache_dir"] = directory
    cache: dict[str, Any] = _WORKER["cache"]
    if which not in cache:
        if which == "truth":
            cache[which] = load_truth(Path(directory) / "truth.json")
        else:
            cache[which] = read_recording(Path(directory) / f"{which}.mcap")
    return cache[which]


def _prepared(directory: str, which: str) -> Any:
    """The scenario's ``which`` spin scan ("spin" | "cube") with its returns prepared
    (:func:`calstation.pipeline.turned`), made once per worker and kept with the recordings."""
    from calstation.pipeline import turned

    _recording(directory, which)  # a new scenario empties the cache first
    cache: dict[str, Any] = _WORKER["cache"]
    key = f"prepared:{which}"
    if key not in cache:
        cache[key] = turned(_recording(directory, which))
    return cache[key]


def _recipe(overrides: str) -> Any:
    """The recipe model, with JSON ``overrides`` deep-merged in and validated."""
    base = _WORKER["loaded"].recipe
    patch = json.loads(overrides)
    if not patch:
        return base
    key = f"recipe:{overrides}"
    if key not in _WORKER:
        _WORKER[key] = apply_overrides(base, patch)
    return _WORKER[key]


def apply_overrides(recipe: Any, patch: dict[str, Any]) -> Any:
    """A copy of the recipe model with ``patch`` (nested mapping) deep-merged in, re-validated
    (so a misspelled setting is an error, not silently ignored)."""
    from calstation.recipes import Recipe

    def merge(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
        out = dict(a)
        for k, v in b.items():
            out[k] = merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
        return out

    try:
        return Recipe.model_validate(merge(recipe.model_dump(), patch))
    except Exception as exc:
        raise BenchError(f"recipe override {patch!r} is invalid: {exc}") from None


def run_task(task: Task) -> dict[str, Any]:
    """Run one task in a worker; never raises: a failure becomes a record with status "failed"
    and the error message."""
    record: dict[str, Any] = {
        "id": task.id,
        "kind": task.kind,
        "scenario": task.scenario,
        "method": task.method,
        "set": task.start_set,
        "index": task.index,
        "variant": task.variant,
    }
    if task.kind == "basin":  # kept with a refused start too: it counts as not converged
        record.update(group=task.landscape["group"], level=task.landscape["level"])
    t0 = time.perf_counter()
    try:
        if task.kind == "simulate":
            _run_simulate(task, record)
        elif task.kind == "initial":
            _run_initial(task, record)
        elif task.kind == "finetune":
            _run_finetune(task, record)
        elif task.kind == "landscape":
            record.update(run_landscape_row(task, _recording, _recipe(task.overrides)))
        elif task.kind == "basin":
            _run_basin(task, record)
        else:
            raise BenchError(f"unknown task kind {task.kind!r}")
        record.setdefault("status", "ok")
    except Exception as exc:
        record["status"] = "failed"
        record["error_message"] = f"{type(exc).__name__}: {exc}"
        from calstation.errors import CalstationError

        if not isinstance(exc, CalstationError):
            record["traceback"] = traceback.format_exc(limit=8)
    record["wall_s"] = time.perf_counter() - t0
    if task.kind in ("initial", "finetune", "basin"):
        record["converged"] = converged(task.method, record)
    return _jsonable(record)  # type: ignore[no-any-return]


def _run_simulate(task: Task, record: dict[str, Any]) -> None:
    scenario = next(s for s in paper_scenarios() if s.name == task.scenario)
    simulate_scenario(_WORKER["recipe_path"], scenario, Path(task.directory))


def _run_initial(task: Task, record: dict[str, Any]) -> None:
    from calstation.engine.initial import initial_calibration

    recipe = _recipe(task.overrides)
    static = _recording(task.directory, "static")
    t0 = time.perf_counter()
    result = initial_calibration(static, recipe.fixtures.static_target, recipe.calibration.initial)
    record["stage_s"] = time.perf_counter() - t0
    record.update(result_fields(result))
    record.update(_evaluate(task.directory, result.H, recipe))
    # the cube checked with the true H: the floor of the paper's metric on this sensor
    truth = _recording(task.directory, "truth")
    record["truth_cube"] = _cube_check(task.directory, truth, recipe)


def _run_finetune(task: Task, record: dict[str, Any]) -> None:
    from calstation import plugins

    recipe = _recipe(task.overrides)
    assert task.start is not None
    start = Extrinsics(*task.start)
    record["start"] = _h_dict(start)
    strategy = plugins.strategy(task.method)
    scan = _prepared(task.directory, scan_of(strategy))
    t0 = time.perf_counter()
    result = strategy_result(strategy, scan.recording, start, recipe, prepared=scan.prepared)
    record["stage_s"] = time.perf_counter() - t0
    record.update(result_fields(result))
    record.update(_evaluate(task.directory, result.H, recipe))


def _run_basin(task: Task, record: dict[str, Any]) -> None:
    """Fine-tune from the task's start (:mod:`calstation.bench.basin`); the estimate, its σ and
    its errors against the truth."""
    from calstation import plugins

    recipe = _recipe(task.overrides)
    assert task.start is not None
    strategy = plugins.strategy(task.method)
    scan = _prepared(task.directory, scan_of(strategy))
    t0 = time.perf_counter()
    result = strategy_result(strategy, scan.recording, Extrinsics(*task.start), recipe,
                             prepared=scan.prepared)
    record.update({"stage_s": time.perf_counter() - t0, **result_fields(result)})
    record.update(against_truth(result.H, _recording(task.directory, "truth")))


def _evaluate(directory: str, H: Extrinsics, recipe: Any) -> dict[str, Any]:
    """Everything measured about an estimate ``H``: errors against the truth, axis errors, the
    paper's cube check on the QA-cube scan, and the reconstruction distortion of that scan. A
    measurement that fails is recorded as ``{"failed": message}``; the estimate stays valid."""
    truth: Extrinsics = _recording(directory, "truth")
    cube = _prepared(directory, "cube")
    out = against_truth(H, truth)
    t0 = time.perf_counter()
    out["cube"] = _cube_check(directory, H, recipe)
    t1 = time.perf_counter()
    try:
        from calstation.engine.metrics import reconstruction_distortion

        out["distortion"] = {
            k: float(v) for k, v in reconstruction_distortion(
                cube.recording, H, truth, prepared=cube.prepared).items()
        }
    except Exception as exc:
        out["distortion"] = {"failed": f"{type(exc).__name__}: {exc}"}
    t2 = time.perf_counter()
    out["eval_timings"] = {"cube_check_s": t1 - t0, "distortion_s": t2 - t1}
    return out


def _cube_check(directory: str, H: Extrinsics, recipe: Any) -> dict[str, Any]:
    """The engine's cube check of the scenario's QA-cube scan with ``H``, as a plain mapping
    (``{"failed": message}`` if the cube could not be measured)."""
    try:
        from calstation.engine.cube import check_cube

        cube = _prepared(directory, "cube")
        check = check_cube(
            cube.recording, H, recipe.fixtures.qa_cube, recipe.qa,
            platter_radius=recipe.fixtures.platter.radius, prepared=cube.prepared,
        )
        return _jsonable(check.to_dict())  # type: ignore[no-any-return]
    except Exception as exc:
        return {"failed": f"{type(exc).__name__}: {exc}"}
