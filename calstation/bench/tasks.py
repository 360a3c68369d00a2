"""What the paper bench runs: its configuration, the fine-tuning methods and the ablation
variants it compares, and its units of work.

Every unit is a small picklable :class:`Task` that carries paths and six numbers, never
recordings; the builders here order them by scenario, so that a worker reads each scenario's
recordings once (:mod:`calstation.bench.worker`).
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypedDict

from calstation.bench.records import LandscapeSpec
from calstation.bench.scenarios import (
    PERTURBATION_SEED,
    PERTURBATION_SETS,
    Scenario,
    paper_scenarios,
    sample_starts,
)
from calstation.engine.frames import Extrinsics
from calstation.jsonvalue import JSONObject

FINE_TUNING_METHODS: tuple[str, ...] = ("shape", "periodicity")
"""The paper's two fine-tuning strategies, run by name through the plugin registry."""


ABLATION_VARIANTS: dict[str, JSONObject] = {
    "default": {},
    "no coarse-to-fine": {"calibration": {"periodicity": {"coarse_to_fine": False}}},
    "gauge ty (paper)": {"calibration": {"periodicity": {"gauge": "ty"}}},
    "paper (no coarse-to-fine, gauge ty)": {
        "calibration": {"periodicity": {"coarse_to_fine": False, "gauge": "ty"}}
    },
}
"""Recipe overrides of the periodicity robustness features compared in the ablation."""

SHAPE_ABLATION_VARIANTS: dict[str, JSONObject] = {
    "default": {},
    "no coarse alignment": {"calibration": {"options": {"shape": {"coarse": False}}}},
    "ry held (no face flatness)": {"calibration": {"options": {"shape": {"estimate_ry": False}}}},
    "box cost only (no known-size cube)": {
        "calibration": {"options": {"shape": {"known_size": False}}}
    },
    "paper (minimal box, joint ry, no coarse)": {
        "calibration": {
            "options": {"shape": {"box": "minimal", "estimate_ry": True, "coarse": False,
                                  "known_size": False}}
        }
    },
}
"""Recipe overrides of the shape strategy's robustness features compared in the ablation."""

ABLATIONS: dict[str, dict[str, JSONObject]] = {
    "periodicity": ABLATION_VARIANTS,
    "shape": SHAPE_ABLATION_VARIANTS,
}
"""Ablation variants per fine-tuning method (variant names are unique across methods, apart
from ``default``, which is the main run)."""


class ScenarioMeta(TypedDict):
    """A scenario in a run's metadata (:class:`~calstation.bench.scenarios.Scenario`'s fields)."""

    name: str
    range_m: float
    pitch_deg: float
    seed: int


class ConfigMeta(TypedDict, total=False):
    """A :class:`BenchConfig` as ``run.json`` keeps it (paths as strings; every key is there in a
    run's own metadata, an older ``run.json`` may lack some)."""

    recipe: str
    out: str
    scenarios: list[ScenarioMeta]
    starts_per_set: int
    workers: int
    methods: list[str]
    landscape_scenario: str | None
    landscape_grid: int
    landscape_translation_m: float
    landscape_rotation_deg: float
    ablation_scenarios: list[str]
    ablation_starts: int
    ablation_variants: list[str]
    shape_ablation_variants: list[str]
    sets: list[str]
    perturbed_methods: list[str] | None
    seed: int
    round_starts: int
    deadline: float | None
    quick: bool
    command: str


class RunMeta(TypedDict, total=False):
    """A bench run's metadata, ``run.json`` (:func:`calstation.bench.runner.run_bench`)."""

    config: ConfigMeta
    command: str
    git_commit: str
    python: str
    platform: str
    cpu_count: int | None
    started_utc: str
    finished_utc: str
    phases_s: dict[str, float]
    starts_completed: int
    cut_by_deadline: bool
    load_start: float | None
    load_end: float | None
    previous_runs: list[RunMeta]
    wall_s: float
    wall_s_total: float
    records: int


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

    def to_dict(self) -> ConfigMeta:
        """JSON-ready description (paths as strings, scenarios as dicts)."""
        return {
            "recipe": str(self.recipe),
            "out": str(self.out),
            "scenarios": [{"name": s.name, "range_m": s.range_m, "pitch_deg": s.pitch_deg,
                           "seed": s.seed} for s in self.scenarios],
            "starts_per_set": self.starts_per_set,
            "workers": self.workers,
            "methods": list(self.methods),
            "landscape_scenario": self.landscape_scenario,
            "landscape_grid": self.landscape_grid,
            "landscape_translation_m": self.landscape_translation_m,
            "landscape_rotation_deg": self.landscape_rotation_deg,
            "ablation_scenarios": list(self.ablation_scenarios),
            "ablation_starts": self.ablation_starts,
            "ablation_variants": list(self.ablation_variants),
            "shape_ablation_variants": list(self.shape_ablation_variants),
            "sets": list(self.sets),
            "perturbed_methods": (None if self.perturbed_methods is None
                                  else list(self.perturbed_methods)),
            "seed": self.seed,
            "round_starts": self.round_starts,
            "deadline": self.deadline,
            "quick": self.quick,
            "command": self.command,
        }


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
    landscape: LandscapeSpec = field(default_factory=LandscapeSpec)


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
    overrides: Mapping[str, object] | None = None,
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


def estimate_wall_time(seconds_per_task: float, config: BenchConfig) -> float:
    """Rough wall time (s) of the fine-tuning phase for ``seconds_per_task`` per fine-tuning."""
    n = len(config.scenarios) * len(config.methods) * (1 + 2 * config.starts_per_set)
    return n * seconds_per_task / max(1, config.workers)
