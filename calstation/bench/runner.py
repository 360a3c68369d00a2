"""Run the paper's experiments in parallel and record every result against the true H.

The run reads top-down: simulate the scenarios, run the initial calibration per scenario, run the
fine-tuning strategies from the initial calibration and from the perturbed starts, sample the cost
landscapes, run the ablation. The units of work (:mod:`calstation.bench.tasks`) run in worker
processes (:mod:`calstation.bench.worker`) through :mod:`calstation.bench.execute`, which appends
each finished task's record to ``records.jsonl``; ``resume`` skips tasks already recorded.
"""

from __future__ import annotations

import json
import os
import platform
import sys
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING

from calstation.atomic import write_atomic
from calstation.bench import BenchError
from calstation.bench.execute import (
    DeadlineReached,
    Executor,
    RecordStore,
    _load,
    _previous_meta,
    _run_phase,
    git_commit,
)
from calstation.bench.landscape import landscape_tasks
from calstation.bench.scenarios import is_simulated
from calstation.bench.tasks import (
    BenchConfig,
    RunMeta,
    Task,
    ablation_tasks,
    finetune_tasks,
    initial_tasks,
    scenario_dir,
)
from calstation.engine.frames import PARAMETER_NAMES, Extrinsics

if TYPE_CHECKING:
    from rich.console import Console


def run_bench(config: BenchConfig, console: Console, resume: bool = False) -> RunMeta:
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
    run = _BenchRun(config, console, resume)
    try:
        with Executor(config.recipe, config.workers) as ex:
            run.simulate(ex)
            initial = run.initial_calibration(ex)
            per_task = run.from_initial(ex, initial)
            run.landscapes(ex)
            run.perturbed_starts(ex, initial, per_task)
    except DeadlineReached:
        run.meta["cut_by_deadline"] = True
        console.print("deadline reached: the phase in progress was cut")
    run.meta["finished_utc"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    run.save()
    return run.meta


class _BenchRun:
    """One run of :func:`run_bench`: its phases, its record store and its metadata, saved to
    ``run.json`` after every phase."""

    def __init__(self, config: BenchConfig, console: Console, resume: bool) -> None:
        self.config = config
        self.console = console
        self.store = RecordStore(config.out / "records.jsonl", resume)
        previous = _previous_meta(config.out) if resume else None
        self.meta: RunMeta = {
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
            self.meta["previous_runs"] = [*previous.pop("previous_runs", []), previous]
        self.t_start = time.monotonic()
        self.phases = self.meta["phases_s"]

    def save(self) -> None:
        """Write the metadata as it stands to ``run.json``."""
        meta = self.meta
        meta["wall_s"] = time.monotonic() - self.t_start
        meta["wall_s_total"] = meta["wall_s"] + sum(
            float(p.get("wall_s", 0.0)) for p in meta.get("previous_runs", [])
        )
        meta["records"] = len(self.store.records)
        meta["load_end"] = _load()
        write_atomic(self.config.out / "run.json", json.dumps(meta, indent=2), "run record")

    def phase(self, name: str, tasks: Sequence[Task], ex: Executor) -> float:
        """Run the phase's tasks not yet recorded; the seconds per task it took (0 if none
        ran)."""
        t = time.monotonic()
        n = _run_phase(ex, self.store, tasks, name, self.console, self.config.deadline)
        dt = time.monotonic() - t
        self.phases[name] = self.phases.get(name, 0.0) + dt
        self.save()
        return dt / n if n else 0.0

    def simulate(self, ex: Executor) -> None:
        """Simulate the scenarios not simulated yet with this recipe and seed."""
        t = time.monotonic()
        _simulate(self.config, ex, self.store, self.console)
        self.phases["simulate"] = time.monotonic() - t

    def initial_calibration(self, ex: Executor) -> dict[str, Extrinsics]:
        """The initial calibration of every scenario; the estimates by scenario name (none
        for a scenario whose calibration failed)."""
        self.phase("initial calibration", initial_tasks(self.config), ex)
        return _initial_estimates(self.store)

    def from_initial(self, ex: Executor, initial: dict[str, Extrinsics]) -> float:
        """Every method from the initial calibration, and the ablation; the seconds per task."""
        config = self.config
        first = finetune_tasks(config, initial, config.scenarios, config.methods, range(0))
        first += ablation_tasks(config, initial)
        order = {s.name: i for i, s in enumerate(config.scenarios)}
        first.sort(key=lambda t: order.get(t.scenario, 0))  # one read per scenario
        return self.phase("fine-tuning from the initial calibration, ablation", first, ex)

    def landscapes(self, ex: Executor) -> None:
        """The cost landscapes, when the configuration names a scenario for them."""
        if self.config.landscape_scenario:
            self.phase("cost landscapes", landscape_tasks(self.config, self.store), ex)

    def perturbed_starts(
        self, ex: Executor, initial: dict[str, Extrinsics], per_task: float
    ) -> None:
        """The perturbed starts in rounds, until ``starts_per_set`` or the deadline."""
        config = self.config
        done = 0
        methods = config.perturbed_methods or config.methods
        while done < config.starts_per_set:
            nxt = self._round_end(initial, methods, done, per_task)
            if nxt is None:
                self.meta["cut_by_deadline"] = True
                break
            tasks = finetune_tasks(
                config, initial, config.scenarios, methods, range(done, nxt), False,
                sets=config.sets,
            )
            dt = self.phase(f"perturbed starts {done + 1}-{nxt} of {config.starts_per_set}",
                            tasks, ex)
            per_task = dt or per_task
            done = nxt
            self.meta["starts_completed"] = done
            self.save()

    def _round_end(
        self, initial: dict[str, Extrinsics], methods: Sequence[str], done: int, per_task: float
    ) -> int | None:
        """Where the round of perturbed starts after the first ``done`` ends: a whole round,
        or with a deadline as many starts as still fit before it (at ``per_task`` seconds per
        task); None when not even one fits."""
        config = self.config
        nxt = min(config.starts_per_set, done + max(1, config.round_starts))
        if config.deadline is None or not per_task > 0:
            return nxt
        # as many starts as still fit before the deadline, up to a whole round
        one = finetune_tasks(config, initial, config.scenarios, methods,
                             range(done, done + 1), False, sets=config.sets)
        need = 1.2 * per_task * len(one)
        fit = int((config.deadline - time.time()) // need) if need > 0 else nxt
        if fit < 1:
            self.console.print(
                f"deadline: stopping after {done} start(s) per set "
                f"(the next start needs ~{need / 60:.0f} min)"
            )
            return None
        return min(nxt, done + fit)


def _simulate(config: BenchConfig, ex: Executor, store: RecordStore, console: Console) -> None:
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
