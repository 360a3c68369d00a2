"""The basin of convergence: the fraction of starts from which each fine-tuning converges,
against the distance of the start from the true H.

Per parameter (tx, tz, ry, rz: one of them off by the level's distance, the others true) and
jointly (all four off, each by 80–100 % of the level's distance with a random sign), at seven
levels out to ±500 mm and ±10°. ty is the gauge (kept true) and rx 0. "Converged" is the bench's
:data:`~calstation.bench.records.CONVERGENCE` for the method; a start the strategy refuses with an
error counts as not converged. The starts are drawn from a fixed seed, so a run is repeatable.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, TypedDict

import numpy as np

from calstation.atomic import write_atomic
from calstation.bench.records import BenchRecord
from calstation.bench.tasks import Task
from calstation.engine.frames import PARAMETER_NAMES, Extrinsics

if TYPE_CHECKING:
    from rich.console import Console

PARAMS = ("tx", "tz", "ry", "rz")
TRANSLATIONS_M = (0.005, 0.020, 0.050, 0.100, 0.200, 0.300, 0.500)
ROTATIONS_DEG = (0.25, 1.0, 2.0, 4.0, 6.0, 8.0, 10.0)
"""The levels: level i moves a translation by TRANSLATIONS_M[i] and a rotation by
ROTATIONS_DEG[i]; the joint starts move all four by level i at once."""
BASIN_SEED = 2027


def _offset(param: str, level: int) -> float:
    """The distance of ``level`` for ``param`` in SI units (m or rad)."""
    if param in ("tx", "tz"):
        return TRANSLATIONS_M[level]
    return math.radians(ROTATIONS_DEG[level])


class BasinStart(TypedDict):
    """One start of the basin: its group (a parameter or "joint"), level, index and H."""

    group: str
    level: int
    index: int
    start: tuple[float, ...]


def basin_starts(truth: Extrinsics, starts: int, seed: int = BASIN_SEED) -> list[BasinStart]:
    """Every start: ``{"group": param or "joint", "level": i, "index": j, "start": (6,)}``."""
    rng = np.random.default_rng(seed)
    out: list[BasinStart] = []
    base = truth.with_(rx=0.0).as_vector()
    for group in (*PARAMS, "joint"):
        for level in range(len(TRANSLATIONS_M)):
            for j in range(starts):
                x = base.copy()
                for p in PARAMS if group == "joint" else (group,):
                    sign = 1.0 if (j % 2 == 0 if group != "joint" else rng.random() < 0.5) else -1.0
                    x[PARAMETER_NAMES.index(p)] += sign * rng.uniform(0.8, 1.0) * _offset(p, level)
                out.append({"group": group, "level": level, "index": j,
                            "start": tuple(float(v) for v in x)})
    return out


def basin_tasks(
    scenario: str, directory: Path, truth: Extrinsics, methods: Sequence[str], starts: int
) -> list[Task]:
    """One fine-tuning task per (method, start)."""
    tasks = []
    for method in methods:
        for s in basin_starts(truth, starts):
            tasks.append(
                Task(
                    f"{scenario}/basin/{method}/{s['group']}/{s['level']}/{s['index']:02d}",
                    "basin",
                    scenario,
                    str(directory),
                    method=method,
                    index=s["index"],
                    start=s["start"],
                    landscape={"group": s["group"], "level": s["level"]},
                )
            )
    return tasks


def _fractions(records: Sequence[BenchRecord], method: str, group: str) -> list[float]:
    out = []
    for level in range(len(TRANSLATIONS_M)):
        sel = [r for r in records
               if r["method"] == method and r.get("group") == group and r.get("level") == level]
        out.append(sum(bool(r.get("converged")) for r in sel) / len(sel) if sel else math.nan)
    return out


def silently_wrong(records: Sequence[BenchRecord]) -> list[BenchRecord]:
    """The estimates that missed the thresholds yet whose σ a station with the default
    accuracy budget (``calibration.accuracy``, over the default platter) would accept: the ones
    a user could not tell from good ones."""
    from calstation.engine.observability import accuracy_problem, predict
    from calstation.engine.result import CalibrationResult
    from calstation.recipes import AccuracySettings, PlatterGeometry

    budget, platter = AccuracySettings(), PlatterGeometry()

    def accepted(r: BenchRecord) -> bool:
        result = CalibrationResult(Extrinsics.from_dict(r["H"]), dict(r.get("sigma", {})), 0.0,
                                   0, r["method"])
        return accuracy_problem(predict(result, budget, platter), budget) is None

    return [r for r in records
            if r.get("status") == "ok" and not r.get("converged") and accepted(r)]


def _level_label(group: str, level: int) -> str:
    if group in ("tx", "tz"):
        return f"{TRANSLATIONS_M[level] * 1e3:g} mm"
    if group in ("ry", "rz"):
        return f"{ROTATIONS_DEG[level]:g}°"
    return f"{TRANSLATIONS_M[level] * 1e3:g} mm / {ROTATIONS_DEG[level]:g}°"


class BasinMeta(TypedDict):
    """How a basin run was made (``basin.json``)."""

    command: str
    git_commit: str
    wall_s: float
    ry_bound_deg: float
    workers: int
    scenario: str
    starts: int
    methods: list[str]


def basin_markdown(records: Sequence[BenchRecord], meta: BasinMeta) -> str:
    """The section for results.md: how it was made, a table per method, the figure."""
    methods = [m for m in meta["methods"] if any(r["method"] == m for r in records)]
    failed = sum(r.get("status") != "ok" for r in records)
    lines = [
        "## Basin of convergence",
        "",
        f"Command: `{meta['command']}` (commit `{meta['git_commit']}`, "
        f"{meta['wall_s'] / 60:.1f} min on {meta['workers']} workers). Scenario "
        f"{meta['scenario']}; from the true H, one parameter off by the level's distance (the "
        "others true) or all four at once (each by 80–100 % of it, random signs); "
        f"{meta['starts']} starts per level, {len(records)} fine-tunings, {failed} of them "
        "refused with an error (not converged). Converged: the thresholds above. Fractions of "
        "the starts that converged:",
        "",
    ]
    if "ry_bound_deg" in meta:
        lines += [
            f"Periodicity searches ry within {meta['ry_bound_deg']:g}° of its start "
            "(`calibration.periodicity.ry_bound_deg`: ry is nearly unobservable and would walk "
            "to a moving bound) and shape within 2.5° (its faces' flatness step), so a start "
            "further off in ry cannot converge.",
            "",
        ]
    for method in methods:
        head = "| start off in | " + " | ".join(
            f"level {i + 1}" for i in range(len(TRANSLATIONS_M))) + " |"
        lines += [f"**{method}**", "", head, "|---" * (len(TRANSLATIONS_M) + 1) + "|"]
        for group in (*PARAMS, "joint"):
            fr = _fractions(records, method, group)
            cells = [f"{_level_label(group, i)}: {f:.0%}" if math.isfinite(f) else "—"
                     for i, f in enumerate(fr)]
            lines.append(f"| {group} | " + " | ".join(cells) + " |")
        lines.append("")
    missed = [r for r in records if r.get("status") == "ok" and not r.get("converged")]
    silent = silently_wrong(records)
    lines += [
        f"Of the {len(missed)} estimates returned outside the thresholds, {len(silent)} "
        + ("has" if len(silent) == 1 else "have") + " a σ "
        "that the default accuracy budget (`calibration.accuracy`) accepts"
        + (": " + ", ".join(r["id"] for r in silent[:8]) if silent else "")
        + "; a station refuses the others by their predicted error.",
        "",
        "![basin of convergence](results/basin.png)",
        "",
    ]
    return "\n".join(lines)


def basin_figure(records: Sequence[BenchRecord], methods: Sequence[str], path: Path) -> None:
    """One panel per parameter and one for the joint starts: converged fraction against the
    start's distance, a line per method."""
    from calstation.bench.figures import METHOD_COLOURS, METHOD_LABELS, _agg, save_figure

    _agg()
    import matplotlib.pyplot as plt

    groups = (*PARAMS, "joint")
    fig, axes = plt.subplots(1, len(groups), figsize=(3.2 * len(groups), 3.0), sharey=True)
    for ax, group in zip(axes, groups, strict=True):
        x = (np.array(TRANSLATIONS_M) * 1e3 if group in ("tx", "tz", "joint")
             else np.array(ROTATIONS_DEG))
        for method in methods:
            fr = _fractions(records, method, group)
            ax.plot(x, fr, "o-", color=METHOD_COLOURS.get(method), label=METHOD_LABELS.get(method,
                                                                                         method))
        ax.set_xscale("log")
        ax.set_ylim(-0.05, 1.05)
        unit = "mm" if group in ("tx", "tz") else "°" if group in ("ry", "rz") else "mm (and °)"
        ax.set_xlabel(f"{group} off by ({unit})")
        ax.grid(True, alpha=0.3)
    axes[0].set_ylabel("converged fraction")
    axes[-1].legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)


def run_basin(
    recipe: Path, out: Path, report_dir: Path, scenario_name: str, methods: Sequence[str],
    starts: int, workers: int, command: str, console: Console,
) -> Path:
    """Simulate the scenario (or reuse it), run every start, write ``basin.md`` and
    ``results/basin.png`` to ``report_dir``; returns the path of ``basin.md``."""
    from calstation.bench.execute import Executor, RecordStore, _run_phase, git_commit
    from calstation.bench.scenarios import load_truth, select_scenarios, simulate_scenario
    from calstation.recipes import load_recipe

    (scenario,) = select_scenarios([scenario_name])
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    data = simulate_scenario(recipe, scenario, out / "scenarios" / scenario.name)
    truth = load_truth(data.directory / "truth.json")
    store = RecordStore(out / "records.jsonl", resume=True)
    tasks = basin_tasks(scenario.name, data.directory, truth, methods, starts)
    with Executor(recipe, workers) as ex:
        _run_phase(ex, store, tasks, "basin of convergence", console)
    ids = {t.id for t in tasks}
    records = [r for r in store.records.values() if r["id"] in ids]
    ry_bound = load_recipe(recipe).recipe.calibration.periodicity.ry_bound_deg
    meta: BasinMeta = {
        "command": command, "git_commit": git_commit(), "wall_s": time.monotonic() - t0,
        "ry_bound_deg": ry_bound,
        "workers": workers, "scenario": f"{scenario.name} ({scenario.range_m:.2f} m, "
        f"{scenario.pitch_deg:.0f}°)", "starts": starts, "methods": list(methods)}
    write_atomic(out / "basin.json", json.dumps(meta, indent=2), "records")
    basin_figure(records, methods, report_dir / "results" / "basin.png")
    path = report_dir / "basin.md"
    write_atomic(path, basin_markdown(records, meta), "bench report")
    return path
