"""Run the paper's experiments in parallel and record every result against the true H.

The run reads top-down: simulate the scenarios, run the initial calibration per scenario, run the
fine-tuning strategies from the initial calibration and from the perturbed starts, sample the cost
landscapes, run the ablation. Every task is a small picklable :class:`Task`; workers (separate
processes, ``spawn``) load a scenario's recordings once and keep them while tasks of the same
scenario arrive (tasks are ordered by scenario), so no big array is pickled per task. Each finished
task appends one JSON record to ``records.jsonl``; ``resume`` skips tasks already recorded.
"""

from __future__ import annotations

import json
import math
import multiprocessing
import os
import platform
import subprocess
import sys
import time
import traceback
import warnings
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from calstation.bench import BenchError
from calstation.bench.scenarios import (
    PERTURBATION_SEED,
    PERTURBATION_SETS,
    Scenario,
    is_simulated,
    load_truth,
    paper_scenarios,
    sample_starts,
    simulate_scenario,
)
from calstation.engine.frames import PARAMETER_NAMES, Extrinsics

FINE_TUNING_METHODS: tuple[str, ...] = ("shape", "periodicity")
"""The paper's two fine-tuning strategies, run by name through the plugin registry."""

CONVERGENCE: dict[str, dict[str, float]] = {
    # the engine issue's acceptance thresholds (DESIGN §8 metrics against the true H)
    "periodicity": {
        "axis_offset_m": 0.5e-3,
        "axis_angle_rad": math.radians(0.1),
        "rz_rad": math.radians(0.05),
    },
    "shape": {"axis_offset_m": 2.0e-3, "axis_angle_rad": math.radians(0.3)},
    # the initial calibration must land inside the paper's set-A box around the truth
    "initial": {
        "tx_m": 0.100,
        "ty_m": 0.100,
        "tz_m": 0.100,
        "ry_rad": math.radians(1.0),
        "rz_rad": math.radians(1.0),
    },
}
"""Per method, the largest error still counted as converged (metres / radians)."""

ABLATION_VARIANTS: dict[str, dict[str, Any]] = {
    "default": {},
    "no coarse-to-fine": {"calibration": {"periodicity": {"coarse_to_fine": False}}},
    "gauge ty (paper)": {"calibration": {"periodicity": {"gauge": "ty"}}},
    "paper (no coarse-to-fine, gauge ty)": {
        "calibration": {"periodicity": {"coarse_to_fine": False, "gauge": "ty"}}
    },
}
"""Recipe overrides of the periodicity robustness features compared in the ablation."""

SHAPE_ABLATION_VARIANTS: dict[str, dict[str, Any]] = {
    "default": {},
    "no coarse alignment": {"calibration": {"options": {"shape": {"coarse": False}}}},
    "ry held (no face flatness)": {"calibration": {"options": {"shape": {"estimate_ry": False}}}},
    "paper (minimal box, joint ry, no coarse)": {
        "calibration": {
            "options": {"shape": {"box": "minimal", "estimate_ry": True, "coarse": False}}
        }
    },
}
"""Recipe overrides of the shape strategy's robustness features compared in the ablation."""

ABLATIONS: dict[str, dict[str, dict[str, Any]]] = {
    "periodicity": ABLATION_VARIANTS,
    "shape": SHAPE_ABLATION_VARIANTS,
}
"""Ablation variants per fine-tuning method (variant names are unique across methods, apart
from ``default``, which is the main run)."""


@dataclass(frozen=True)
class BenchConfig:
    """What one bench run does.

    ``starts_per_set`` perturbed starts in each of sets A and B per scenario and method (the paper
    used 50); the landscape is sampled on a ``landscape_grid`` × ``landscape_grid`` grid for
    ``landscape_scenario``; the ablation runs periodicity from the initial calibration and the
    first ``ablation_starts`` set-B starts of ``ablation_scenarios``.
    """

    recipe: Path
    out: Path
    scenarios: tuple[Scenario, ...]
    starts_per_set: int = 50
    workers: int = 2
    methods: tuple[str, ...] = FINE_TUNING_METHODS
    landscape_scenario: str | None = "D6"
    landscape_grid: int = 31
    landscape_translation_m: float = 0.020
    landscape_rotation_deg: float = 2.0
    ablation_scenarios: tuple[str, ...] = ("D1", "D9")
    ablation_starts: int = 5
    ablation_variants: tuple[str, ...] = tuple(ABLATION_VARIANTS)
    shape_ablation_variants: tuple[str, ...] = tuple(SHAPE_ABLATION_VARIANTS)
    sets: tuple[str, ...] = ("A", "B")
    perturbed_methods: tuple[str, ...] | None = None
    seed: int = PERTURBATION_SEED
    round_starts: int = 50
    deadline: float | None = None
    quick: bool = False
    command: str = ""

    @classmethod
    def full(cls, recipe: Path, out: Path, workers: int = 2, command: str = "") -> BenchConfig:
        """The paper's protocol: nine scenarios, 50 + 50 starts."""
        return cls(recipe, out, tuple(paper_scenarios()), workers=workers, command=command)

    @classmethod
    def quick_config(
        cls, recipe: Path, out: Path, workers: int = 1, command: str = ""
    ) -> BenchConfig:
        """A small subset for the test suite: one scenario (D5); both methods from the initial
        calibration, periodicity from one set-A start; a 3 × 3 landscape; coarse-to-fine on/off
        from the initial calibration."""
        d5 = next(s for s in paper_scenarios() if s.name == "D5")
        return cls(
            recipe,
            out,
            (d5,),
            starts_per_set=1,
            workers=workers,
            sets=("A",),
            perturbed_methods=("periodicity",),
            landscape_scenario="D5",
            landscape_grid=3,
            ablation_scenarios=("D5",),
            ablation_starts=0,
            ablation_variants=("default", "no coarse-to-fine"),
            shape_ablation_variants=(),
            quick=True,
            command=command,
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description (paths as strings, scenarios as dicts)."""
        d = asdict(self)
        d["recipe"] = str(self.recipe)
        d["out"] = str(self.out)
        return d


@dataclass(frozen=True)
class Task:
    """One unit of work for a worker. Carries paths and six numbers, never recordings."""

    id: str
    kind: str  # "simulate" | "initial" | "finetune" | "landscape" | "basin"
    scenario: str
    directory: str
    method: str = "initial"
    start_set: str = "init"  # "init" | "A" | "B"
    index: int = 0
    start: tuple[float, ...] | None = None
    variant: str = "default"
    overrides: str = "{}"  # JSON recipe overrides
    landscape: dict[str, Any] = field(default_factory=dict)


# --- worker side -----------------------------------------------------------------------------
_WORKER: dict[str, Any] = {}


def _thread_env(threads: int) -> dict[str, str]:
    return {
        name: str(threads)
        for name in (
            "OMP_NUM_THREADS",
            "OPENBLAS_NUM_THREADS",
            "MKL_NUM_THREADS",
            "NUMEXPR_NUM_THREADS",
        )
    }


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


def _h_dict(h: Extrinsics) -> dict[str, float]:
    return {n: float(getattr(h, n)) for n in PARAMETER_NAMES}


def scan_of(strategy: Any) -> str:
    """Which of a scenario's scans ("spin" or "cube") a fine-tuning strategy runs on."""
    return "cube" if getattr(strategy, "fixture", "spin_target") == "qa_cube" else "spin"


def against_truth(H: Extrinsics, truth: Extrinsics) -> dict[str, Any]:
    """An estimate's per-parameter errors and axis errors against the truth (the axis errors as
    ``{"failed": message}`` if they cannot be computed)."""
    out: dict[str, Any] = {
        "truth": _h_dict(truth),
        "error": {n: float(getattr(H, n) - getattr(truth, n)) for n in PARAMETER_NAMES},
    }
    try:
        from calstation.engine.metrics import axis_errors

        out["axis"] = {k: float(v) for k, v in axis_errors(H, truth).items()}
    except Exception as exc:
        out["axis"] = {"failed": f"{type(exc).__name__}: {exc}"}
    return out


def _evaluate(directory: str, H: Extrinsics, recipe: Any) -> dict[str, Any]:
    """Everything measured about an estimate ``H``: errors against the truth, axis errors, the
    paper's cube check on the QA-cube scan, and the reconstruction distortion of that scan. A
    measurement that fails is recorded as ``{"failed": message}``; the estimate stays valid."""
    truth: Extrinsics = _recording(directory, "truth")
    cube_rec = _recording(directory, "cube")
    out = against_truth(H, truth)
    t0 = time.perf_counter()
    out["cube"] = _cube_check(directory, H, recipe)
    t1 = time.perf_counter()
    try:
        from calstation.engine.metrics import reconstruction_distortion

        out["distortion"] = {
            k: float(v) for k, v in reconstruction_distortion(cube_rec, H, truth).items()
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

        check = check_cube(
            _recording(directory, "cube"), H, recipe.fixtures.qa_cube, recipe.qa,
            platter_radius=recipe.fixtures.platter.radius,
        )
        return _jsonable(check.to_dict())  # type: ignore[no-any-return]
    except Exception as exc:
        return {"failed": f"{type(exc).__name__}: {exc}"}


def _jsonable(x: Any) -> Any:
    """Nested data with numpy scalars/arrays turned into plain JSON types."""
    import numpy as np

    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None if math.isnan(x) else (1e308 if x > 0 else -1e308)
    if isinstance(x, str | int | float | bool) or x is None:
        return x
    return str(x)


def converged(method: str, record: dict[str, Any]) -> bool:
    """Whether a record meets :data:`CONVERGENCE` for its method (False if it failed)."""
    if record.get("status") != "ok":
        return False
    limits = CONVERGENCE.get(method if method in CONVERGENCE else "shape", {})
    for key, limit in limits.items():
        if key.startswith("axis_"):
            value = record["axis"].get(key)
        else:
            value = record["error"].get(key.rsplit("_", 1)[0])
        if value is None or not abs(float(value)) <= limit:
            return False
    return True


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
            from calstation.bench.landscape import run_landscape_row

            record.update(run_landscape_row(task, _recording, _recipe(task.overrides)))
        elif task.kind == "basin":
            from calstation.bench.basin import run_basin_task

            record.update(run_basin_task(task, _recording, _recipe(task.overrides)))
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


def result_fields(result: Any) -> dict[str, Any]:
    return {
        "H": _h_dict(result.H),
        "sigma": {k: float(v) for k, v in dict(result.sigma).items()},
        "cost": float(result.cost),
        "iterations": int(result.iterations),
        "strategy": str(result.strategy),
        "timings": {k: float(v) for k, v in dict(result.timings).items()},
        "diagnostics": _jsonable(_small_diagnostics(dict(result.diagnostics))),
    }


def _small_diagnostics(diag: dict[str, Any]) -> dict[str, Any]:
    """Diagnostics without bulky arrays (keep scalars, short lists)."""
    out: dict[str, Any] = {}
    for k, v in diag.items():
        if isinstance(v, str | int | float | bool) or v is None:
            out[k] = v
        elif isinstance(v, list | tuple) and len(v) <= 64:
            out[k] = list(v)
        elif hasattr(v, "shape") and getattr(v, "size", 1e9) <= 64:
            out[k] = v
    return out


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
    recording = _recording(task.directory, scan_of(strategy))
    t0 = time.perf_counter()
    result = strategy.run(recording, start, recipe)
    record["stage_s"] = time.perf_counter() - t0
    record.update(result_fields(result))
    record.update(_evaluate(task.directory, result.H, recipe))


# --- main process side ---------------------------------------------------------------------------
class RecordStore:
    """``records.jsonl`` in the output folder: one JSON record per finished task, appended and
    flushed at once so an interrupted run keeps what it finished."""

    def __init__(self, path: Path, resume: bool) -> None:
        self.path = path
        self.records: dict[str, dict[str, Any]] = {}
        if resume and path.is_file():
            for line in path.read_text().splitlines():
                if line.strip():
                    try:
                        rec = json.loads(line)
                    except ValueError:
                        continue  # a line cut short by a kill
                    self.records[rec["id"]] = rec
            with path.open("w") as fh:  # rewrite without any torn line
                for rec in self.records.values():
                    fh.write(json.dumps(rec) + "\n")
        else:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text("")

    def add(self, record: dict[str, Any]) -> None:
        """Keep ``record`` and append it to the file."""
        self.records[record["id"]] = record
        with self.path.open("a") as fh:
            fh.write(json.dumps(record) + "\n")

    def of_kind(self, kind: str) -> list[dict[str, Any]]:
        """Every record of ``kind``."""
        return [r for r in self.records.values() if r["kind"] == kind]


ProgressFactory = Callable[[str, int], "Progress"]


class Progress:
    """A rich progress bar on a terminal; a log line every 20 s (and at the end) otherwise."""

    def __init__(self, console: Any, description: str, total: int) -> None:
        self.console = console
        self.description = description
        self.total = total
        self.done = 0
        self.failed = 0
        self.t0 = time.monotonic()
        self.last_log = self.t0
        self._bar: Any = None
        self._task: Any = None

    def __enter__(self) -> Progress:
        if self.console.is_terminal:
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                Progress as RichProgress,
                TextColumn,
                TimeElapsedColumn,
                TimeRemainingColumn,
            )

            self._bar = RichProgress(
                TextColumn("[bold]{task.description}"),
                BarColumn(),
                MofNCompleteColumn(),
                TextColumn("{task.fields[failed]} failed"),
                TimeElapsedColumn(),
                TimeRemainingColumn(),
                console=self.console,
            )
            self._bar.__enter__()
            self._task = self._bar.add_task(self.description, total=self.total, failed=0)
        else:
            self.console.print(f"{self.description}: {self.total} tasks")
        return self

    def advance(self, ok: bool) -> None:
        """One task finished (``ok`` False if it failed)."""
        self.done += 1
        self.failed += 0 if ok else 1
        if self._bar is not None:
            self._bar.update(self._task, advance=1, failed=self.failed)
            return
        now = time.monotonic()
        if now - self.last_log >= 20.0 or self.done == self.total:
            self.last_log = now
            elapsed = now - self.t0
            eta = elapsed / self.done * (self.total - self.done) if self.done else float("nan")
            self.console.print(
                f"{self.description}: {self.done}/{self.total} done, {self.failed} failed, "
                f"{elapsed:.0f} s elapsed, ~{eta:.0f} s left"
            )

    def __exit__(self, *exc: object) -> None:
        if self._bar is not None:
            self._bar.__exit__(None, None, None)


class Executor:
    """Runs tasks in ``workers`` spawned processes (or in this process when ``workers`` is 1)."""

    def __init__(self, recipe: Path, workers: int) -> None:
        self.recipe = recipe
        self.workers = max(1, workers)
        self._pool: Any = None

    def __enter__(self) -> Executor:
        if self.workers > 1:
            threads = max(1, (os.cpu_count() or 1) // self.workers)
            saved = {k: os.environ.get(k) for k in _thread_env(threads)}
            os.environ.update(_thread_env(threads))  # inherited by the spawned workers
            try:
                ctx = multiprocessing.get_context("spawn")
                self._pool = ctx.Pool(
                    self.workers, initializer=_init_worker, initargs=(str(self.recipe),)
                )
            finally:
                for k, v in saved.items():
                    if v is None:
                        os.environ.pop(k, None)
                    else:
                        os.environ[k] = v
        else:
            _init_worker(str(self.recipe))
        return self

    def map(self, tasks: Sequence[Task]) -> Iterator[dict[str, Any]]:
        """Results as they finish (any order)."""
        if self._pool is None:
            for t in tasks:
                yield run_task(t)
        else:
            yield from self._pool.imap_unordered(run_task, tasks, chunksize=1)

    def __exit__(self, *exc: object) -> None:
        if self._pool is not None:
            if exc[0] is None:
                self._pool.close()
            else:
                self._pool.terminate()
            self._pool.join()


def _run_phase(
    executor: Executor,
    store: RecordStore,
    tasks: Sequence[Task],
    description: str,
    console: Any,
    deadline: float | None = None,
) -> int:
    """Run the tasks not yet recorded; returns how many ran. Raises :class:`DeadlineReached`
    when ``deadline`` (Unix time) passes before they are all done."""
    todo = list({t.id: t for t in tasks if t.id not in store.records}.values())
    if not todo:
        return 0
    if deadline is not None and time.time() > deadline:
        raise DeadlineReached
    with Progress(console, description, len(todo)) as bar:
        for rec in executor.map(todo):
            store.add(rec)
            bar.advance(rec.get("status") == "ok")
            if deadline is not None and time.time() > deadline and bar.done < len(todo):
                raise DeadlineReached
    return len(todo)


def scenario_dir(config: BenchConfig, scenario: Scenario) -> Path:
    """Where a scenario's recordings live."""
    return config.out / "scenarios" / scenario.name


def initial_tasks(config: BenchConfig) -> list[Task]:
    """One initial calibration per scenario."""
    return [
        Task(f"{s.name}/initial", "initial", s.name, str(scenario_dir(config, s)))
        for s in config.scenarios
    ]


def finetune_tasks(
    config: BenchConfig,
    initial: dict[str, Extrinsics],
    scenarios: Iterable[Scenario],
    methods: Iterable[str],
    indices: range,
    include_init: bool = True,
    variant: str = "default",
    overrides: dict[str, Any] | None = None,
    sets: Sequence[str] = ("A", "B"),
) -> list[Task]:
    """Fine-tuning tasks, ordered by scenario so each worker reads a scenario once: from the
    initial calibration (if ``include_init``), then the starts numbered ``indices`` of each of
    ``sets`` (start i is the same in every run: see :func:`sample_starts`)."""
    tasks: list[Task] = []
    all_names = [s.name for s in paper_scenarios()]
    methods = list(methods)
    suffix = "" if variant == "default" else f"@{variant}"
    for s in scenarios:
        if s.name not in initial:
            continue  # its initial calibration failed: nothing to start from
        h0 = initial[s.name]
        starts: list[tuple[str, int, Extrinsics]] = [("init", 0, h0)] if include_init else []
        for set_name in sets:
            sampled = sample_starts(
                h0, PERTURBATION_SETS[set_name], indices.stop, all_names.index(s.name),
                config.seed,
            )
            starts += [(set_name, i, sampled[i]) for i in indices]
        for method in methods:
            for set_name, i, h in starts:
                tasks.append(
                    Task(
                        f"{s.name}/{method}/{set_name}/{i:03d}{suffix}",
                        "finetune",
                        s.name,
                        str(scenario_dir(config, s)),
                        method=method,
                        start_set=set_name,
                        index=i,
                        start=tuple(float(x) for x in h.as_vector()),
                        variant=variant,
                        overrides=json.dumps(overrides or {}, sort_keys=True),
                    )
                )
    return tasks


def git_commit(cwd: Path | None = None) -> str:
    """``git rev-parse HEAD`` of the source tree (with ``+dirty`` if calstation's sources have
    uncommitted changes), ``$CALSTATION_SOURCE_COMMIT`` when the code runs from an export of a
    commit, or ``"unknown"``."""
    pinned = os.environ.get("CALSTATION_SOURCE_COMMIT")
    if pinned:  # running from an exported tree (git archive) of that commit
        return f"{pinned} (clean export)"
    root = cwd or Path(__file__).resolve().parents[2]
    try:
        head = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no", "--",
             "calstation", "plugins", "recipes"],
            cwd=root,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        return head + ("+dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


class DeadlineReached(Exception):
    """Raised inside :func:`run_bench` when the deadline passes in the middle of a phase."""


def run_bench(config: BenchConfig, console: Any, resume: bool = False) -> dict[str, Any]:
    """Run every phase of the bench; return the run's metadata (also written to ``run.json``).

    Phases: simulate; initial calibration; both fine-tunings from the initial calibration with
    the ablation; cost landscapes; then the perturbed starts in rounds of
    ``config.round_starts`` set-A and set-B starts per scenario and method, until
    ``config.starts_per_set`` (a worker reads and prepares each scenario's scans once per
    round). With a ``config.deadline`` (Unix time) a round holds only the starts that will
    finish in time (estimated from the previous phase) and a phase still running at the
    deadline is cut; the metadata then
    says how many starts per set were completed (``starts_completed``), which the report uses.
    Records go to ``config.out / "records.jsonl"``; simulated scenarios are reused when the recipe
    and seed match.
    """
    config.out.mkdir(parents=True, exist_ok=True)
    store = RecordStore(config.out / "records.jsonl", resume)
    previous = _previous_meta(config.out) if resume else None
    meta: dict[str, Any] = {
        "config": config.to_dict(),
        "command": config.command,
        "git_commit": git_commit(),
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "phases_s": {},
        "starts_completed": 0,
        "cut_by_deadline": False,
        "load_start": _load(),
    }
    if previous is not None:
        meta["previous_runs"] = [*previous.pop("previous_runs", []), previous]
    t_start = time.monotonic()
    phases: dict[str, float] = meta["phases_s"]

    def save() -> None:
        meta["wall_s"] = time.monotonic() - t_start
        meta["wall_s_total"] = meta["wall_s"] + sum(
            float(p.get("wall_s", 0.0)) for p in meta.get("previous_runs", [])
        )
        meta["records"] = len(store.records)
        meta["load_end"] = _load()
        (config.out / "run.json").write_text(json.dumps(meta, indent=2))

    def phase(name: str, tasks: Sequence[Task], ex: Executor) -> float:
        t = time.monotonic()
        n = _run_phase(ex, store, tasks, name, console, config.deadline)
        dt = time.monotonic() - t
        phases[name] = phases.get(name, 0.0) + dt
        save()
        return dt / n if n else 0.0

    try:
        with Executor(config.recipe, config.workers) as ex:
            t = time.monotonic()
            _simulate(config, ex, store, console)
            phases["simulate"] = time.monotonic() - t
            phase("initial calibration", initial_tasks(config), ex)
            initial = _initial_estimates(store)
            first = finetune_tasks(config, initial, config.scenarios, config.methods, range(0))
            first += ablation_tasks(config, initial)
            order = {s.name: i for i, s in enumerate(config.scenarios)}
            first.sort(key=lambda t: order.get(t.scenario, 0))  # one read per scenario
            per_task = phase("fine-tuning from the initial calibration, ablation", first, ex)
            if config.landscape_scenario:
                from calstation.bench.landscape import landscape_tasks

                phase("cost landscapes", landscape_tasks(config, store), ex)
            done = 0
            methods = config.perturbed_methods or config.methods
            while done < config.starts_per_set:
                nxt = min(config.starts_per_set, done + max(1, config.round_starts))
                if config.deadline is not None and per_task > 0:
                    # as many starts as still fit before the deadline, up to a whole round
                    one = finetune_tasks(config, initial, config.scenarios, methods,
                                         range(done, done + 1), False, sets=config.sets)
                    need = 1.2 * per_task * len(one)
                    fit = int((config.deadline - time.time()) // need) if need > 0 else nxt
                    if fit < 1:
                        console.print(
                            f"deadline: stopping after {done} start(s) per set "
                            f"(the next start needs ~{need / 60:.0f} min)"
                        )
                        meta["cut_by_deadline"] = True
                        break
                    nxt = min(nxt, done + fit)
                tasks = finetune_tasks(
                    config, initial, config.scenarios, methods, range(done, nxt), False,
                    sets=config.sets,
                )
                dt = phase(f"perturbed starts {done + 1}-{nxt} of {config.starts_per_set}",
                           tasks, ex)
                per_task = dt or per_task
                done = nxt
                meta["starts_completed"] = done
                save()
    except DeadlineReached:
        meta["cut_by_deadline"] = True
        console.print("deadline reached: the phase in progress was cut")
    meta["finished_utc"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    save()
    return meta


def _load() -> float | None:
    """The 1-minute load average (None where the system does not report one)."""
    try:
        return os.getloadavg()[0]
    except OSError:
        return None


def _previous_meta(out: Path) -> dict[str, Any] | None:
    path = out / "run.json"
    try:
        return dict(json.loads(path.read_text())) if path.is_file() else None
    except ValueError:
        return None


def ablation_tasks(config: BenchConfig, initial: dict[str, Extrinsics]) -> list[Task]:
    """Periodicity and shape with each robustness feature switched off, on the ablation
    subset: from the initial calibration and the first ``config.ablation_starts`` set-B starts
    (the default variant's tasks are the main run's, with the same ids, so they run once)."""
    chosen = [s for s in config.scenarios if s.name in config.ablation_scenarios]
    tasks: list[Task] = []
    for method, variants in (
        ("periodicity", config.ablation_variants),
        ("shape", config.shape_ablation_variants),
    ):
        if method not in config.methods:
            continue
        for variant in variants:
            tasks += finetune_tasks(
                config,
                initial,
                chosen,
                [method],
                range(config.ablation_starts),
                variant=variant,
                overrides=ABLATIONS[method][variant],
                sets=("B",),
            )
    return tasks


def _simulate(config: BenchConfig, ex: Executor, store: RecordStore, console: Any) -> None:
    from calstation.recipes import load_recipe

    sha = load_recipe(config.recipe).sha256
    todo = [
        Task(f"{s.name}/simulate", "simulate", s.name, str(scenario_dir(config, s)))
        for s in config.scenarios
        if not is_simulated(s, scenario_dir(config, s), sha)
    ]
    # simulations are always redone when missing, even on resume
    for t in todo:
        store.records.pop(t.id, None)
    _run_phase(ex, store, todo, "simulating scenarios", console)
    bad = [s.name for s in config.scenarios if not is_simulated(s, scenario_dir(config, s), sha)]
    if bad:
        msgs = [store.records.get(f"{n}/simulate", {}).get("error_message", "?") for n in bad]
        detail = ", ".join(f"{n} ({m})" for n, m in zip(bad, msgs, strict=True))
        raise BenchError(f"simulation failed for {detail}")


def _initial_estimates(store: RecordStore) -> dict[str, Extrinsics]:
    out = {}
    for rec in store.of_kind("initial"):
        if rec.get("status") == "ok":
            out[rec["scenario"]] = Extrinsics(*(rec["H"][n] for n in PARAMETER_NAMES))
    return out


def estimate_wall_time(seconds_per_task: float, config: BenchConfig) -> float:
    """Rough wall time (s) of the fine-tuning phase for ``seconds_per_task`` per fine-tuning."""
    n = len(config.scenarios) * len(config.methods) * (1 + 2 * config.starts_per_set)
    return n * seconds_per_task / max(1, config.workers)


__all__ = [
    "ABLATIONS",
    "ABLATION_VARIANTS",
    "CONVERGENCE",
    "SHAPE_ABLATION_VARIANTS",
    "BenchConfig",
    "DeadlineReached",
    "Executor",
    "RecordStore",
    "Task",
    "apply_overrides",
    "converged",
    "estimate_wall_time",
    "finetune_tasks",
    "git_commit",
    "run_bench",
    "run_task",
    "scenario_dir",
]
