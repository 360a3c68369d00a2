"""The targetless start on many simulated stations: the paper's nine scenarios plus three more,
several seeds each. Every spin scan is fine-tuned twice, from the platter's chord
(:mod:`calstation.engine.targetless`) and from the L-target's initial calibration, and both results
are held to the bench's convergence thresholds against the true H.

The seed changes the simulated station (its true H's small ry and tz, the placements, the
noise), so each run is a different station, not a different draw of one.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, TypedDict

from calstation.atomic import write_atomic
from calstation.bench.records import Measured
from calstation.bench.scenarios import Scenario
from calstation.engine.frames import Extrinsics

if TYPE_CHECKING:
    from rich.console import Console

EXTRA_SCENARIOS: tuple[tuple[str, float, float], ...] = (
    ("E1", 0.9, 40.0),
    ("E2", 1.1, 50.0),
    ("E3", 1.4, 35.0),
)
"""Stations the paper did not measure: (name, range m, pitch °)."""

SEED_BASE = 3000

GEOMETRY: dict[str, tuple[float, ...]] = {
    "tz_mm": (-100.0, -50.0, -25.0, 25.0, 50.0, 100.0),
    "ry_deg": (-2.0, -1.0, 1.0, 2.0),
}
"""The start's two assumptions, broken on purpose: the station's true tz set to each value (the
chord gives only |tz|, poorly near 0), or its true ry moved by each value (the start takes
ry = 0). D5's geometry otherwise. (From about 150 mm of tz the default spin target is no longer
cut by the scan plane in both half-turns, and the periodicity fails even from the true H.)"""


def targetless_scenarios() -> list[Scenario]:
    """The paper's D1–D9 and :data:`EXTRA_SCENARIOS` (seeds are given per run)."""
    from calstation.bench.scenarios import paper_scenarios

    return [*paper_scenarios(), *(Scenario(n, r, p, 0) for n, r, p in EXTRA_SCENARIOS)]


class Errors(TypedDict):
    """An estimate against the truth (:func:`_errors`)."""

    axis: Measured
    error: dict[str, float]
    converged: bool


class StartFit(TypedDict, total=False):
    """One fine-tuning of a station's scan from one start: its errors, or why it failed."""

    status: str  # "ok" | "failed"
    message: str
    axis: Measured
    error: dict[str, float]
    converged: bool
    start: Errors
    tz_from_chord_m: float
    candidates: object
    time_s: float


class TargetlessRecord(TypedDict):
    """One simulated station: its fine-tuning from the platter's chord and from the L-target."""

    scenario: str
    range_m: float
    pitch_deg: float
    seed: int
    method: str
    truth: dict[str, float]
    targetless: StartFit
    l_target: StartFit


class GeometryRow(TypedDict, total=False):
    """One station whose true tz or ry breaks the targetless start's assumptions."""

    param: str
    value: float
    scenario: str
    seed: int
    truth: dict[str, float]
    status: str  # "ok" | "failed" | "station"
    message: str
    same: bool
    tz_from_chord_m: float
    start_axis_offset_m: float
    from_truth_offset_m: float
    from_truth_angle_rad: float
    axis_offset_m: float
    axis_angle_rad: float


class TargetlessMeta(TypedDict):
    """How a targetless sweep was made."""

    command: str
    git_commit: str
    wall_s: float
    method: str
    seeds: str
    geometry: list[GeometryRow]


def _errors(H: Extrinsics, truth: Extrinsics, method: str) -> Errors:
    """An estimate against the truth, and whether it meets the bench's thresholds for
    ``method`` (:func:`calstation.bench.records.converged`)."""
    from calstation.bench.records import against_truth, converged

    e = against_truth(H, truth)
    e["status"] = "ok"
    return {"axis": e["axis"], "error": e["error"], "converged": converged(method, e)}


def run_case(recipe: Path, scenario: Scenario, seed: int, out: Path, method: str
             ) -> TargetlessRecord:
    """Simulate one station, fine-tune its scan from both starts; its record."""
    from calstation import plugins
    from calstation.pipeline import Scans, calibrate, turned
    from calstation.recipes import load_recipe
    from calstation.recordings.reader import read_recording

    loaded = load_recipe(recipe)
    rc = loaded.recipe
    folder = out / f"{scenario.name}-s{seed}"
    files = plugins.simulator().simulate_run(loaded, folder, seed=seed, range_m=scenario.range_m,
                         pitch_deg=scenario.pitch_deg, progress=False)
    strategy = plugins.strategy(method)
    recording = read_recording(files["spin" if strategy.fixture == "spin_target" else "cube"])
    truth = recording.truth
    assert truth is not None
    spin = turned(recording)
    t0 = time.perf_counter()
    targetless: StartFit
    try:
        done = calibrate(rc, Scans(spin=spin), strategy)
        result, start = done.result, done.start
    except Exception as exc:  # a failure is a result of the sweep, kept with its reason
        targetless = {"status": "failed", "message": f"{type(exc).__name__}: {exc}",
                      "converged": False}
    else:
        e = _errors(result.H, truth, method)
        targetless = {"status": "ok", "axis": e["axis"], "error": e["error"],
                      "converged": e["converged"], "start": _errors(start.H, truth, method),
                      "tz_from_chord_m": start.diagnostics["tz_from_chord_m"],
                      "candidates": result.diagnostics["start"]["candidates"]}
    targetless["time_s"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    l_target: StartFit
    try:
        from_l = calibrate(rc, Scans(spin=spin, static=read_recording(files["static"])),
                           strategy).result
    except Exception as exc:
        l_target = {"status": "failed", "message": f"{type(exc).__name__}: {exc}",
                    "converged": False}
    else:
        e = _errors(from_l.H, truth, method)
        l_target = {"status": "ok", "axis": e["axis"], "error": e["error"],
                    "converged": e["converged"]}
    l_target["time_s"] = time.perf_counter() - t1
    return {"scenario": scenario.name, "range_m": scenario.range_m,
            "pitch_deg": scenario.pitch_deg, "seed": seed, "method": method,
            "truth": {"tz": truth.tz, "ry": truth.ry},
            "targetless": targetless, "l_target": l_target}


SAME_M = 1e-4
SAME_RAD = math.radians(0.05)
"""Two fine-tunings of one scan landed in the same place: axes within these (the periodicity's
ry is flat to within a few hundredths of a degree, so two starts may leave it that far apart)."""


def run_geometry_case(recipe: Path, scenario: Scenario, seed: int, param: str, value: float,
                      out: Path, method: str) -> GeometryRow:
    """One station whose true tz is ``value`` mm (``param`` ``tz_mm``) or whose true ry is
    moved by ``value`` degrees (``ry_deg``); the fine-tuning from the platter's chord against
    the one from the true H on the same scan (the start is in the basin when both land in the
    same place)."""
    import yaml

    from calstation import plugins
    from calstation.engine.metrics import axis_errors
    from calstation.pipeline import Scans, calibrate, turned
    from calstation.plugins.cost_strategies import run_strategy
    from calstation.recipes import load_recipe
    from calstation.recordings.reader import read_recording

    simulator = plugins.simulator()
    nominal = simulator.truth(load_recipe(recipe), seed=seed, range_m=scenario.range_m,
                              pitch_deg=scenario.pitch_deg)
    H = (nominal.with_(tz=value * 1e-3) if param == "tz_mm"
         else nominal.with_(ry=nominal.ry + math.radians(value)))
    data = yaml.safe_load(recipe.read_text())
    data["simulation"]["truth"] = {"H": H.as_dict()}
    folder = out / f"{scenario.name}-{param}{value:+g}"
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "recipe.yaml"
    write_atomic(path, yaml.safe_dump(data, sort_keys=False), "recipe")
    loaded = load_recipe(path)
    files = simulator.simulate_run(loaded, folder / "scans", seed=seed, progress=False)
    strategy = plugins.strategy(method)
    spin = turned(read_recording(files["spin" if strategy.fixture == "spin_target"
                                         else "cube"]))
    record: GeometryRow = {"param": param, "value": value, "scenario": scenario.name,
                              "seed": seed, "truth": H.as_dict()}
    try:
        from_truth, _ = run_strategy(strategy, spin.recording, H, loaded.recipe,
                                     prepared=spin.prepared)
    except Exception as exc:  # the station itself is beyond the strategy: not the start's doing
        record.update({"status": "station", "message": f"even from the true H: {exc}",
                       "same": False})
        return record
    try:
        done = calibrate(loaded.recipe, Scans(spin=spin), strategy)
        result, start = done.result, done.start
    except Exception as exc:  # a failure is a result of the sweep, kept with its reason
        record.update({"status": "failed", "message": f"{type(exc).__name__}: {exc}",
                       "same": False})
        return record
    same = axis_errors(result.H, from_truth.H)
    truth = axis_errors(result.H, H)
    record.update({
        "status": "ok", "tz_from_chord_m": start.diagnostics["tz_from_chord_m"],
        "start_axis_offset_m": axis_errors(start.H, H)["axis_offset_m"],
        "same": bool(same["axis_offset_m"] <= SAME_M and same["axis_angle_rad"] <= SAME_RAD),
        "from_truth_offset_m": same["axis_offset_m"],
        "from_truth_angle_rad": same["axis_angle_rad"],
        "axis_offset_m": truth["axis_offset_m"],
        "axis_angle_rad": truth["axis_angle_rad"]})
    return record


def geometry_markdown(rows: Sequence[GeometryRow]) -> list[str]:
    """The table of the start's assumptions broken on purpose."""
    if not rows:
        return []
    r0 = rows[0]
    lines = [
        "",
        f"**The start's assumptions, broken on purpose** ({r0['scenario']}, seed {r0['seed']}): "
        "the station's true tz set to each value (the chord gives |tz| only, and poorly near 0), "
        "or its true ry moved (the start takes ry = 0). *Same* means the fine-tuning from the "
        "platter lands within 0.1 mm and 0.05° of the fine-tuning from the true H on the same "
        "scan: the start was inside the strategy's basin (how close that lands to the truth is "
        "the strategy's own accuracy, shown beside it).",
        "",
        "| station | \\|tz\\| from the chord mm | start's axis offset mm | same as from the "
        "truth | axis offset mm / direction ° against the truth |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        what = (f"tz = {r['value']:+g} mm" if r["param"] == "tz_mm"
                else f"ry {r['value']:+g}° off nominal")
        if r["status"] != "ok":
            lines.append(f"| {what} | — | — | no: {r['message'][:150]} | — |")
            continue
        lines.append(
            f"| {what} | {r['tz_from_chord_m'] * 1e3:.1f} | {r['start_axis_offset_m'] * 1e3:.1f} "
            f"| {'yes' if r['same'] else 'NO'} | {r['axis_offset_m'] * 1e3:.3f} / "
            f"{math.degrees(r['axis_angle_rad']):.3f} |")
    return lines


def targetless_markdown(records: Sequence[TargetlessRecord], meta: TargetlessMeta) -> str:
    """The section for results.md."""
    n = len(records)
    conv_t = sum(r["targetless"]["converged"] for r in records)
    conv_l = sum(r["l_target"]["converged"] for r in records)
    lines = [
        "## The targetless start",
        "",
        f"Command: `{meta['command']}` (commit `{meta['git_commit']}`, "
        f"{meta['wall_s'] / 60:.1f} min). The {meta['method']} fine-tuning of each spin scan "
        "from the platter's chord (no L-target) and from the L-target's initial calibration, "
        "against the true H and the bench's convergence thresholds; D1–D9 are the paper's "
        "range × pitch, "
        f"E1–E3 three more; seeds {meta['seeds']} (each a different simulated station).",
        "",
        f"**Converged: {conv_t}/{n} from the platter ({100.0 * conv_t / max(n, 1):.1f} %), "
        f"{conv_l}/{n} from the L-target.**",
        "",
        "| scenario | runs | converged from the platter | from the L-target | start's axis "
        "offset mm (median / max) | start's rz error ° (max) | axis offset mm from the platter "
        "(max) |",
        "|---|---|---|---|---|---|---|",
    ]
    for name in dict.fromkeys(r["scenario"] for r in records):
        sel = [r for r in records if r["scenario"] == name]
        ok = [r["targetless"] for r in sel if r["targetless"]["status"] == "ok"]
        starts = sorted(float(t["start"]["axis"].get("axis_offset_m", math.nan)) * 1e3 for t in ok)
        rz = [abs(math.degrees(t["start"]["error"]["rz"])) for t in ok]
        final = [float(t["axis"].get("axis_offset_m", math.nan)) * 1e3 for t in ok]
        r0 = sel[0]
        lines.append(
            f"| {name} ({r0['range_m']:.2f} m, {r0['pitch_deg']:.0f}°) | {len(sel)} | "
            f"{sum(r['targetless']['converged'] for r in sel)} | "
            f"{sum(r['l_target']['converged'] for r in sel)} | "
            + (f"{starts[len(starts) // 2]:.1f} / {max(starts):.1f} | {max(rz):.3f} | "
               f"{max(final):.3f} |" if ok else "— | — | — |"))
    missed = [r for r in records if not r["targetless"]["converged"]]
    if missed:
        lines += ["", "Not converged from the platter:", ""]
        for r in missed:
            t = r["targetless"]
            axis = t.get("axis", {})
            why = t.get("message") or (
                f"axis offset {float(axis['axis_offset_m']) * 1e3:.2f} mm, "
                f"direction {math.degrees(float(axis['axis_angle_rad'])):.3f}°")
            lines.append(f"- {r['scenario']} seed {r['seed']}: {why[:300]}")
    lines += geometry_markdown(meta.get("geometry", []))
    lines += ["", "![targetless start](results/targetless.png)", ""]
    return "\n".join(lines)


def targetless_figure(records: Sequence[TargetlessRecord], path: Path) -> None:
    """The start's distance from the truth against the final one (the targetless start's basin:
    how far from the truth its starts land, and whether they converge)."""
    from calstation.bench.figures import _agg, save_figure

    _agg()
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.0, 3.4))
    for converged, colour, label in ((True, "tab:green", "converged"),
                                     (False, "tab:red", "not converged")):
        sel = [r["targetless"] for r in records if r["targetless"]["status"] == "ok"
               and r["targetless"]["converged"] is converged]
        ax.scatter([float(t["start"]["axis"]["axis_offset_m"]) * 1e3 for t in sel],
                   [max(float(t["axis"]["axis_offset_m"]) * 1e3, 1e-4) for t in sel],
                   s=14, color=colour, label=f"{label} ({len(sel)})")
    ax.set_xlabel("start's axis offset from the truth (mm)")
    ax.set_ylabel("fine-tuned axis offset (mm)")
    ax.set_yscale("log")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)


def run_targetless(recipe: Path, out: Path, report_dir: Path, method: str, seeds: int,
                   scenario_names: Sequence[str] | None, command: str, console: Console,
                   geometry: bool = True) -> Path:
    """Every scenario × seed in turn, then (with ``geometry``) the :data:`GEOMETRY` stations on
    D5; writes ``targetless.md`` and ``results/targetless.png`` to ``report_dir`` and the records
    to ``out/records.json`` and ``out/geometry.json``; returns the path of the section."""
    import shutil

    from calstation import plugins
    from calstation.bench.execute import git_commit

    plugins.load_plugins()
    chosen = targetless_scenarios()
    if scenario_names:
        wanted = {n.strip().upper() for n in scenario_names}
        chosen = [s for s in chosen if s.name in wanted]
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    records: list[TargetlessRecord] = []
    for i, scenario in enumerate(chosen):
        for k in range(seeds):
            seed = SEED_BASE + 100 * k + i
            record = run_case(recipe, scenario, seed, out, method)
            records.append(record)
            t = record["targetless"]
            console.print(f"{scenario.name} seed {seed}: "
                          + ("converged" if t["converged"] else f"NOT converged ({t['status']})")
                          + f" from the platter, {t['time_s']:.1f} s")
            shutil.rmtree(out / f"{scenario.name}-s{seed}", ignore_errors=True)
            write_atomic(out / "records.json", json.dumps(records, indent=2), "records")
    rows: list[GeometryRow] = []
    if geometry:
        d5 = next(s for s in targetless_scenarios() if s.name == "D5")
        for param, values in GEOMETRY.items():
            for value in values:
                row = run_geometry_case(recipe, d5, SEED_BASE + 4, param, value, out, method)
                rows.append(row)
                console.print(f"{param} {value:+g}: "
                              + ("same as from the truth" if row["same"] else "NOT the same"))
                shutil.rmtree(out / f"D5-{param}{value:+g}", ignore_errors=True)
                write_atomic(out / "geometry.json", json.dumps(rows, indent=2), "records")
    meta: TargetlessMeta = {
        "command": command, "git_commit": git_commit(), "wall_s": time.monotonic() - t0,
        "method": method, "seeds": f"{SEED_BASE} + 100·k + scenario index, k < {seeds}",
        "geometry": rows}
    targetless_figure(records, report_dir / "results" / "targetless.png")
    path = report_dir / "targetless.md"
    write_atomic(path, targetless_markdown(records, meta), "bench report")
    return path
