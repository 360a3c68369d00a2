"""Accuracy against platter speed: one scenario simulated with the spin and cube scans at several
platter speeds and the sensor's own line rate, each fine-tuning run from the initial calibration,
measured against the true H.

A slower platter gives more lines per turn (1 rpm at 1000 lines/s: 60 000 lines), a faster one
fewer; the recipe's other settings stay as they are, except the lidar's points per line where a
turn would make more returns than a simulated scan may hold.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, TypedDict

from calstation.atomic import write_atomic
from calstation.engine.frames import PARAMETER_NAMES

if TYPE_CHECKING:
    from rich.console import Console

    from calstation.bench.scenarios import Scenario


def speed_recipe(recipe: Path, rpm: float, out: Path) -> tuple[Path, int]:
    """A copy of ``recipe`` whose spin and cube scans turn at ``rpm``, written to ``out``, and
    the lidar's points per line in it: the recipe's, or fewer where a turn at ``rpm`` would make
    more returns than a scan may hold (:data:`calstation.recipes.MAX_SCAN_POINTS`); the line rate
    stays the sensor's."""
    import yaml

    from calstation.recipes import MAX_SCAN_POINTS, load_recipe

    base = load_recipe(recipe).recipe
    data = yaml.safe_load(recipe.read_text())
    for step in ("spin_scan", "cube_scan"):
        data["steps"][step]["rpm"] = rpm
    ppl = 0
    if base.simulation is not None:
        lidar, accel = base.simulation.lidar, base.simulation.turntable.acceleration_rpm_s
        ppl = lidar.points_per_line
        for scan in (base.steps.spin_scan, base.steps.cube_scan):
            seconds = scan.settle_s + rpm / accel + scan.revolutions * 60.0 / rpm
            ppl = min(ppl, int(0.98 * MAX_SCAN_POINTS / (seconds * lidar.line_rate_hz)))
        data["simulation"]["lidar"]["points_per_line"] = ppl
    write_atomic(out, yaml.safe_dump(data, sort_keys=False), "recipe", make_parents=True)
    return out, ppl


class SpeedRecord(TypedDict, total=False):
    """One fine-tuning at one platter speed (``records.json``)."""

    rpm: float
    method: str
    points: int
    lines: int
    points_per_line: int
    simulate_s: float
    status: str  # "ok" | "failed"
    message: str
    axis_offset_m: float
    axis_angle_rad: float
    rz_error_rad: float
    sigma: dict[str, float]
    H: dict[str, float]
    stage_s: float


class SpeedMeta(TypedDict):
    """How a speed sweep was made."""

    command: str
    git_commit: str
    wall_s: float
    scenario: str
    line_rate_hz: float


def run_speed_case(recipe: Path, scenario: Scenario, rpm: float, out: Path,
                   methods: Sequence[str]) -> list[SpeedRecord]:
    """Simulate ``scenario`` at ``rpm``, calibrate, fine-tune with each method from the initial
    calibration; one record per method (a refused fine-tuning is a record with its message)."""
    from calstation import plugins
    from calstation.bench.records import scan_of
    from calstation.bench.scenarios import load_truth, simulate_scenario
    from calstation.engine.initial import initial_calibration
    from calstation.engine.metrics import axis_errors
    from calstation.recipes import load_recipe
    from calstation.recordings.reader import read_recording

    path, ppl = speed_recipe(recipe, rpm, out / f"recipe-{rpm:g}rpm.yaml")
    t0 = time.perf_counter()
    data = simulate_scenario(path, scenario, out / "scenarios" / f"{scenario.name}-{rpm:g}rpm")
    simulate_s = time.perf_counter() - t0
    rc = load_recipe(path).recipe
    truth = load_truth(data.directory / "truth.json")
    initial = initial_calibration(read_recording(data.static), rc.fixtures.static_target,
                                  rc.calibration.initial)
    records: list[SpeedRecord] = []
    for method in methods:
        strategy = plugins.strategy(method)
        rec = read_recording(getattr(data, scan_of(strategy)))
        record: SpeedRecord = {"rpm": rpm, "method": method, "points": rec.n_points,
                                  "lines": rec.n_lines, "points_per_line": ppl,
                                  "simulate_s": simulate_s}
        t1 = time.perf_counter()
        try:
            result = strategy.run(rec, initial.H, rc)
        except Exception as exc:  # a refusal is a result of the sweep, recorded with its reason
            record.update({"status": "failed", "message": f"{type(exc).__name__}: {exc}"})
        else:
            e = axis_errors(result.H, truth)
            record.update({
                "status": "ok",
                "axis_offset_m": float(e["axis_offset_m"]),
                "axis_angle_rad": float(e["axis_angle_rad"]),
                "rz_error_rad": float(e["rz_error"]),
                "sigma": {k: float(v) for k, v in dict(result.sigma).items()},
                "H": {n: float(getattr(result.H, n)) for n in PARAMETER_NAMES},
            })
        record["stage_s"] = time.perf_counter() - t1
        records.append(record)
        del rec
    return records


def speed_markdown(records: Sequence[SpeedRecord], meta: SpeedMeta) -> str:
    """The section for results.md."""
    lines = [
        "## Accuracy against platter speed",
        "",
        f"Command: `{meta['command']}` (commit `{meta['git_commit']}`, "
        f"{meta['wall_s'] / 60:.1f} min). Scenario {meta['scenario']}, the recipe's line rate "
        f"({meta['line_rate_hz']:g} lines/s); the spin and cube scans at each speed, every other "
        "setting as in the recipe; each fine-tuning from the initial calibration, against the "
        "true H; one simulated run per speed (the scenario's seed), so a row's scatter is one "
        "draw of the noise. Where a turn would make more returns than a simulated scan may hold "
        "(25 M), the lidar's points per line are lowered to fit and the line rate kept.",
        "",
        "| platter speed | lines per turn | points per line | method | returns | axis offset mm "
        "| axis direction ° | rz error ° | time s |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in sorted(records, key=lambda r: (r["rpm"], r["method"])):
        per_turn = meta["line_rate_hz"] * 60.0 / r["rpm"]
        if r["status"] == "ok":
            cells = (f"{r['axis_offset_m'] * 1e3:.3f} | {math.degrees(r['axis_angle_rad']):.3f} | "
                     f"{math.degrees(r['rz_error_rad']):+.4f}")
        else:
            cells = f"refused: {r['message'][:120]} | — | —"
        lines.append(f"| {r['rpm']:g} rpm | {per_turn:,.0f} | {r['points_per_line']} | "
                     f"{r['method']} | "
                     f"{r['points'] / 1e6:.1f} M | {cells} | {r['stage_s']:.1f} |")
    lines += ["", "![accuracy against platter speed](results/speed.png)", ""]
    return "\n".join(lines)


def speed_figure(records: Sequence[SpeedRecord], path: Path) -> None:
    """Axis offset and direction error against platter speed, a line per method."""
    from calstation.bench.figures import METHOD_COLOURS, METHOD_LABELS, _agg, save_figure

    _agg()
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(8.0, 3.0))
    for method in sorted({r["method"] for r in records}):
        ok = sorted((r for r in records if r["method"] == method and r["status"] == "ok"),
                    key=lambda r: r["rpm"])
        rpm = [r["rpm"] for r in ok]
        style = {"color": METHOD_COLOURS.get(method), "label": METHOD_LABELS.get(method, method)}
        axes[0].plot(rpm, [r["axis_offset_m"] * 1e3 for r in ok], "o-", **style)
        axes[1].plot(rpm, [math.degrees(r["axis_angle_rad"]) for r in ok], "o-", **style)
    for ax, label in zip(axes, ("axis offset (mm)", "axis direction error (°)"), strict=True):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("platter speed (rpm)")
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)


def run_speed(recipe: Path, out: Path, report_dir: Path, scenario_name: str,
              methods: Sequence[str], speeds: Sequence[float], command: str,
              console: Console) -> Path:
    """Every speed in turn (one at a time: a slow turn holds up to 25 M returns); writes
    ``speed.md`` and ``results/speed.png`` to ``report_dir``; returns the path of speed.md."""
    from calstation import plugins
    from calstation.bench.execute import git_commit
    from calstation.bench.scenarios import select_scenarios
    from calstation.recipes import load_recipe

    plugins.load_plugins()
    (scenario,) = select_scenarios([scenario_name])
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    records: list[SpeedRecord] = []
    for rpm in speeds:
        console.print(f"platter speed {rpm:g} rpm …")
        records += run_speed_case(recipe, scenario, rpm, out, methods)
        write_atomic(out / "records.json", json.dumps(records, indent=2), "records")
    rate = load_recipe(recipe).recipe.simulation
    meta: SpeedMeta = {
        "command": command, "git_commit": git_commit(), "wall_s": time.monotonic() - t0,
        "scenario": f"{scenario.name} ({scenario.range_m:.2f} m, {scenario.pitch_deg:.0f}°)",
        "line_rate_hz": float(rate.lidar.line_rate_hz) if rate is not None else math.nan}
    speed_figure(records, report_dir / "results" / "speed.png")
    path = report_dir / "speed.md"
    write_atomic(path, speed_markdown(records, meta), "bench report")
    return path
