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
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, cast

from calstation.bench import BenchError
from calstation.bench.landscape import run_landscape_row
from calstation.bench.records import (
    BenchRecord,
    Measured,
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
from calstation.jsonvalue import JSONObject
from calstation.plugins.cost_strategies import strategy_result

if TYPE_CHECKING:
    from calstation.pipeline import Turned
    from calstation.recipes import LoadedRecipe, Recipe
    from calstation.recordings.recorded import Recording


@dataclass
class _Worker:
    """What a worker process keeps between tasks: the recipe, its overridden copies, and the
    current scenario's recordings, truth and prepared scans."""

    recipe_path: Path
    loaded: LoadedRecipe
    recipes: dict[str, Recipe] = field(default_factory=dict)
    directory: str | None = None
    recordings: dict[str, Recording] = field(default_factory=dict)
    truth: Extrinsics | None = None
    prepared: dict[str, Turned] = field(default_factory=dict)

    def scenario(self, directory: str) -> None:
        """Forget the previous scenario's data when a task of another one arrives."""
        if self.directory != directory:
            self.recordings, self.truth, self.prepared = {}, None, {}
            self.directory = directory


_STATE: list[_Worker] = []
"""This worker's state (one element once :func:`_init_worker` ran)."""


def _init_worker(recipe_path: str) -> None:
    """Load the recipe and the plugins once per worker process."""
    warnings.simplefilter("ignore")
    os.environ.setdefault("MPLBACKEND", "Agg")
    from calstation import plugins
    from calstation.recipes import load_recipe

    _STATE[:] = [_Worker(Path(recipe_path), load_recipe(recipe_path))]
    plugins.load_plugins()


def _worker() -> _Worker:
    if not _STATE:
        raise BenchError("the bench worker was not initialised")
    return _STATE[0]


def _recording(directory: str, which: str) -> Recording:
    """The scenario's ``which`` recording ("static" | "spin" | "cube"), read once per worker and
    kept until a task of another scenario arrives."""
    from calstation.recordings.reader import read_recording

    state = _worker()
    state.scenario(directory)
    if which not in state.recordings:
        state.recordings[which] = read_recording(Path(directory) / f"{which}.mcap")
    return state.recordings[which]


def _truth(directory: str) -> Extrinsics:
    """The scenario's true H (its ``truth.json``), read once per worker like the recordings."""
    state = _worker()
    state.scenario(directory)
    if state.truth is None:
        state.truth = load_truth(Path(directory) / "truth.json")
    return state.truth


def _prepared(directory: str, which: str) -> Turned:
    """The scenario's ``which`` spin scan ("spin" | "cube") with its returns prepared
    (:func:`calstation.pipeline.turned`, of the whole recording: its ``recording`` is set), made
    once per worker and kept with the recordings."""
    from calstation.pipeline import turned

    recording = _recording(directory, which)  # a new scenario empties the cache first
    state = _worker()
    if which not in state.prepared:
        state.prepared[which] = turned(recording)
    return state.prepared[which]


def _recipe(overrides: str) -> Recipe:
    """The recipe model, with JSON ``overrides`` deep-merged in and validated."""
    state = _worker()
    base = state.loaded.recipe
    patch = json.loads(overrides)
    if not patch:
        return base
    if overrides not in state.recipes:
        state.recipes[overrides] = apply_overrides(base, patch)
    return state.recipes[overrides]


def apply_overrides(recipe: Recipe, patch: Mapping[str, object]) -> Recipe:
    """A copy of the recipe model with ``patch`` (nested mapping) deep-merged in, re-validated
    (so a misspelled setting is an error, not silently ignored)."""
    from calstation.recipes import Recipe

    def merge(a: Mapping[str, object], b: Mapping[str, object]) -> dict[str, object]:
        out = dict(a)
        for k, v in b.items():
            below = out.get(k)
            out[k] = merge(below, v) if isinstance(v, dict) and isinstance(below, dict) else v
        return out

    try:
        return Recipe.model_validate(merge(recipe.model_dump(), patch))
    except Exception as exc:
        raise BenchError(f"recipe override {patch!r} is invalid: {exc}") from None


def run_task(task: Task) -> BenchRecord:
    """Run one task in a worker; never raises: a failure becomes a record with status "failed"
    and the error message."""
    record: BenchRecord = {
        "id": task.id,
        "kind": task.kind,
        "scenario": task.scenario,
        "method": task.method,
        "set": task.start_set,
        "index": task.index,
        "variant": task.variant,
    }
    if task.kind == "basin":  # kept with a refused start too: it counts as not converged
        record["group"], record["level"] = task.landscape["group"], task.landscape["level"]
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
    # cast: _jsonable keeps the record's keys and shapes, it only makes its numbers JSON-safe
    return cast("BenchRecord", _jsonable(record))


def _run_simulate(task: Task, record: BenchRecord) -> None:
    scenario = next(s for s in paper_scenarios() if s.name == task.scenario)
    simulate_scenario(_worker().recipe_path, scenario, Path(task.directory))


def _run_initial(task: Task, record: BenchRecord) -> None:
    from calstation.engine.initial import initial_calibration

    recipe = _recipe(task.overrides)
    static = _recording(task.directory, "static")
    t0 = time.perf_counter()
    result = initial_calibration(static, recipe.fixtures.static_target, recipe.calibration.initial)
    record["stage_s"] = time.perf_counter() - t0
    record.update(result_fields(result))
    record.update(_evaluate(task.directory, result.H, recipe))
    # the cube checked with the true H: the floor of the paper's metric on this sensor
    truth = _truth(task.directory)
    record["truth_cube"] = _cube_check(task.directory, truth, recipe)


def _run_finetune(task: Task, record: BenchRecord) -> None:
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


def _run_basin(task: Task, record: BenchRecord) -> None:
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
    record.update(against_truth(result.H, _truth(task.directory)))


def _evaluate(directory: str, H: Extrinsics, recipe: Recipe) -> BenchRecord:
    """Everything measured about an estimate ``H``: errors against the truth, axis errors, the
    paper's cube check on the QA-cube scan, and the reconstruction distortion of that scan. A
    measurement that fails is recorded as ``{"failed": message}``; the estimate stays valid."""
    truth = _truth(directory)
    cube = _prepared(directory, "cube")
    against = against_truth(H, truth)
    t0 = time.perf_counter()
    cube_check = _cube_check(directory, H, recipe)
    t1 = time.perf_counter()
    distortion: Measured
    try:
        from calstation.engine.metrics import reconstruction_distortion

        assert cube.recording is not None  # a whole recording, prepared
        distortion = {
            k: float(v) for k, v in reconstruction_distortion(
                cube.recording, H, truth, prepared=cube.prepared).items()
        }
    except Exception as exc:
        distortion = {"failed": f"{type(exc).__name__}: {exc}"}
    t2 = time.perf_counter()
    against["cube"], against["distortion"] = cube_check, distortion
    against["eval_timings"] = {"cube_check_s": t1 - t0, "distortion_s": t2 - t1}
    return against


def _cube_check(directory: str, H: Extrinsics, recipe: Recipe) -> JSONObject:
    """The engine's cube check of the scenario's QA-cube scan with ``H``, as a plain mapping
    (``{"failed": message}`` if the cube could not be measured)."""
    try:
        from calstation.engine.cube import check_cube

        cube = _prepared(directory, "cube")
        assert cube.recording is not None  # a whole recording, prepared
        check = check_cube(
            cube.recording, H, recipe.fixtures.qa_cube, recipe.qa,
            platter_radius=recipe.fixtures.platter.radius, prepared=cube.prepared,
        )
        plain = _jsonable(check.to_dict())
        assert isinstance(plain, dict)  # the check's fields by name
        return plain
    except Exception as exc:
        return {"failed": f"{type(exc).__name__}: {exc}"}
