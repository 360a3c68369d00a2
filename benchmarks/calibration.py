"""Time the calibration engine on simulated recordings and print the figures, each with the
accuracy against the simulator's truth beside it.

    .venv/bin/python benchmarks/calibration.py [--recipe R] [--range 1.25] [--pitch 45]
        [--seed 1] [--repeat 3] [--out DIR] [--scaling] [--compare REV]

Simulates one run (static, spin and cube scans) unless DIR already holds one, then times, each
``--repeat`` times on freshly read recordings:

- reading the three recordings;
- the initial calibration;
- periodicity fine-tuning from the recording (preparation of the spin scan included), and the
  two parts of the station's path: the per-line work done while the spin scan runs
  (:class:`calstation.engine.spinscan.SpinScanBuilder`), then what is left when the scan ends
  (finishing the preparation and fine-tuning), which is the operator's wait;
- shape fine-tuning and the cube check;
- the station's cube step, in a process of its own: the pipeline's cube stage
  (``calstation.pipeline.stages.with_cube``; with the shipped recipes' range model, the cube's
  known-size fit with the range model combined with the spin target's fine-tuning and its
  refits, then the cube check under the combination:
  :func:`calstation.engine.joint.combine_with_cube_scan`), on scans prepared as a station has
  them and with the engine preloaded as a station preloads it (``calstation.station.preload``):
  ``cube stage``; and the operator's wait after the last scan, ``cube step after last scan``:
  the stage and the final H's judgement against the budget, or the judgement alone where the
  station makes the stage in the cube scan's turn fits while the cube turns (with the range
  model). Its accuracy (the combined H, the range offset and the incidence bias against the
  simulator's truth, the check's edge error) is printed beside it.

It prints the peak memory (the process's peak resident set), the processing ÷ acquisition ratio
(processing after the scans, as at a station, ÷ the scans' own duration; and the same with
everything processed from the files), and the targets of docs/performance.md with PASS/MISS:
read ≤ 0.25 s, periodicity after the scan ≤ 1.0 s, shape ≤ 1.0 s, cube check ≤ 0.3 s (and of
a 0.4 m cube centred on the platter ≤ 1 s, simulated beside the run), processing ÷ acquisition
≤ 0.2, peak memory ≤ 1 GB (the station's path ≤ 700 MB). ``--station-runs DIR`` prints beside
them the wait at the station over the capability sweep's runs in DIR (``ry_sweep.py station``):
the median and p95 of the fine calibration ready after the spin scan, of the result ready after
the last (cube) scan, and of the cube check's time. ``--scaling`` adds spin scans of about
0.5, 1, 2 and 4 M points (line rate 159–635 Hz, and 15.75 rpm for 4 M). ``--compare REV`` measures
another git revision side by side (a temporary worktree, the same recordings, runs alternated
A, B, A, B) and prints both with their ratio, and whether their estimates are identical
(``--their-recipe``: the recipe REV reads, when its schema lacks settings of this revision's). The
load average is printed at the start and end: figures taken on a busy machine are pessimistic.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
ENVIRONMENT = dict(os.environ)
"""The environment as given, for the measurements' processes: importing the engine here (to
simulate) sets one BLAS thread for this process and its children, which a revision without
that setting must not inherit."""
TARGETS = {
    "read": 0.25,
    "periodicity after scan": 1.0,
    "shape": 1.0,
    "cube check": 0.3,
    "cube check, 0.4 m cube": 1.0,
    "ratio": 0.2,
    "peak memory MB": 1024.0,
    "station peak memory MB": 700.0,
}
STATION = "station (own process)"
CUBE_STEP = "cube step after last scan"
"""The stage that times the station's cube step with the range model (:func:`measure_cube_step`)."""
CUBE_STAGE = "cube stage"
"""The pipeline's cube stage the cube step takes: made while the cube turns, or after the scan."""
LARGE_CUBE = {"fixtures.qa_cube.edge": 0.4, "fixtures.qa_cube.offset": [0.0, 0.0]}
"""The large cube a recipe validation accepts: 0.4 m, centred on the 585 mm platter."""
SCALING = {0.5: (159.0, 20.0), 1.0: (317.0, 20.0), 2.0: (635.0, 20.0), 4.0: (1000.0, 15.75)}
"""million spin-scan points → (line rate Hz, rpm) with the default 1000 points per line"""


def peak_mb() -> float:
    """The process's peak resident set so far (MB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _timed(fn: Callable[[], Any]) -> tuple[float, Any]:
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def simulate(recipe_path: Path, out: Path, seed: int, range_m: float, pitch: float,
             patch: dict[str, Any] | None = None) -> None:
    """Simulate the run into ``out`` unless it is there already; ``patch`` maps dotted recipe
    keys (``"steps.spin_scan.rpm"``) to values."""
    if (out / "truth.json").exists():
        return
    import yaml
    from calstation_sim import simulate_run

    from calstation.recipes import LoadedRecipe, parse_recipe

    data = yaml.safe_load(recipe_path.read_text())
    for key, value in (patch or {}).items():
        *path, name = key.split(".")
        node = data
        for part in path:
            node = node.setdefault(part, {})
        node[name] = value
    text = yaml.safe_dump(data)
    loaded = LoadedRecipe(parse_recipe(text, str(recipe_path)), None, text)
    t, _ = _timed(lambda: simulate_run(
        loaded, out, seed=seed, range_m=range_m, pitch_deg=pitch, progress=False))
    print(f"simulated run in {t:.1f} s → {out}", flush=True)


def measure(recipe_path: Path, out: Path, with_shape: bool = True) -> dict[str, Any]:
    """One measurement of every stage on freshly read recordings; seconds, accuracy, memory."""
    from calstation.engine.cube import check_cube
    from calstation.engine.initial import initial_calibration
    from calstation.engine.metrics import axis_errors
    from calstation.engine.spinscan import from_recording
    from calstation.plugins.cost_strategies import PeriodicityStrategy, ShapeStrategy
    from calstation.recipes import load_recipe
    from calstation.recordings.reader import read_recording

    rc = load_recipe(recipe_path).recipe
    t: dict[str, float] = {}
    mem: dict[str, float] = {}
    _preload()
    t["read"], recs = _timed(
        lambda: {k: read_recording(out / f"{k}.mcap") for k in ("static", "spin", "cube")})
    mem["read"] = peak_mb()
    truth = recs["spin"].truth
    t["initial"], initial = _timed(lambda: initial_calibration(
        recs["static"], rc.fixtures.static_target, rc.calibration.initial))
    t["periodicity"], per = _timed(lambda: PeriodicityStrategy().run(recs["spin"], initial.H, rc))
    mem["periodicity"] = peak_mb()
    results = {"initial": initial.H, "periodicity": per.H}
    # the cube scan's returns prepared once, by the first stage that reads them (as the
    # calibration pipeline hands them on): shape's time includes it, else the cube check's
    cube: dict[str, Any] = {}

    def prepared_cube() -> Any:
        if "scan" not in cube:
            cube["scan"] = from_recording(recs["cube"])
        return cube["scan"]

    if with_shape:
        t["shape"], shp = _timed(lambda: ShapeStrategy().run_prepared(
            prepared_cube(), initial.H, rc))
        results["shape"] = shp.H
        mem["shape"] = peak_mb()
    t["cube check"], check = _timed(lambda: check_cube(
        recs["cube"], per.H, rc.fixtures.qa_cube, rc.qa,
        platter_radius=rc.fixtures.platter.radius, prepared=prepared_cube()))
    mem["cube check"] = peak_mb()
    acquisition = sum(_duration(r) for r in recs.values())
    accuracy = {}
    if truth is not None:
        for name, H in results.items():
            e = axis_errors(H, truth)
            accuracy[name] = {"offset_mm": e["axis_offset_m"] * 1e3,
                              "direction_deg": math.degrees(e["axis_angle_rad"]),
                              "ry_deg": math.degrees(e["ry_error"])}
    return {
        "t": t, "mem": mem, "accuracy": accuracy, "acquisition_s": acquisition,
        "points": {k: r.n_points for k, r in recs.items()},
        "edge_error_mm": check.edge_error * 1e3, "cube_passed": bool(check.passed),
        "iterations": per.iterations,
    }


def _preload() -> None:
    """Import the engine first: a station has it loaded before its scans end
    (``calstation.station.preload.preload_engine`` imports it, Open3D included, when a run
    starts)."""
    import open3d  # noqa: F401

    import calstation.engine.cube
    import calstation.engine.initial
    import calstation.engine.periodicity
    import calstation.engine.shape  # noqa: F401


def measure_station(recipe_path: Path, out: Path) -> dict[str, Any]:
    """The station's path in a process of its own (for its memory): the spin scan fed line by
    line to the preparation as it would arrive, then finished and fine-tuned. Empty on a
    revision without it."""
    try:
        from calstation.drivers import EncoderSample
        from calstation.engine.periodicity import periodicity_fine_tune_scan
        from calstation.engine.spinscan import SpinScanBuilder
    except ImportError:
        return {}
    from calstation.engine.initial import initial_calibration
    from calstation.engine.metrics import axis_errors
    from calstation.recipes import load_recipe
    from calstation.recordings.reader import read_recording

    rc = load_recipe(recipe_path).recipe
    _preload()
    static = read_recording(out / "static.mcap")
    start = initial_calibration(static, rc.fixtures.static_target, rc.calibration.initial).H
    spin = read_recording(out / "spin.mcap")
    builder = SpinScanBuilder(spin.counts_per_revolution, spin.encoder_direction,
                              spin.encoder_latency_s)
    builder.write_encoder(EncoderSample(int(a), int(b))
                          for a, b in zip(spin.encoder_t_ns, spin.encoder_count, strict=True))
    for line in spin.lines():
        builder.write_line(line)
    truth = spin.truth
    # a station holds the lines it has prepared, not the recording: the last line too (its
    # arrays are views of the recording's, which it would keep)
    del spin, line

    def after() -> Any:
        return periodicity_fine_tune_scan(builder.finish(), start, rc.calibration.periodicity,
                                          platter_radius=rc.fixtures.platter.radius)

    t_after, res = _timed(after)
    e = axis_errors(res.H, truth) if truth is not None else None
    return {
        "t": {"spin per-line work": builder.during_s, "periodicity after scan": t_after},
        "peak_mb": peak_mb(),
        "accuracy": None if e is None else {
            "offset_mm": e["axis_offset_m"] * 1e3,
            "direction_deg": math.degrees(e["axis_angle_rad"]),
            "ry_deg": math.degrees(e["ry_error"])},
    }


def measure_cube_step(recipe_path: Path, out: Path) -> dict[str, Any]:
    """The station's cube step in a process of its own: the recipe's strategy fine-tuned on its
    prepared scan, then, timed, the pipeline's cube stage (``calstation.pipeline.stages.
    with_cube``: for a spin-target strategy with the lidar's range model,
    :func:`calstation.engine.joint.combine_with_cube_scan`'s known-size cube fit, combination
    and refits on the spin scan, then the cube check under the combined H) and what the station
    runs after the last (cube) scan ends, ``seconds``. A station that makes that stage in the
    cube scan's turn fits, while the cube turns (:func:`stage_made_while_turning`), then only
    predicts the final H's error and judges it against the budget; else it runs the stage
    after the scan. The engine's modules are imported first as the station preloads them (this
    revision's or the compared one's ``calstation.station.preload.ENGINE_MODULES``); both scans
    are prepared before the wait, as a station prepares them while it scans. Seconds, and the
    combined estimate's accuracy against the simulator's truth. Empty when the compared
    revision's engine has no such stage for this revision's pipeline to run."""
    import importlib

    try:
        from calstation.pipeline import turned
        from calstation.pipeline.stages import with_cube
        from calstation.station.preload import ENGINE_MODULES
    except ImportError:
        return {}
    from calstation import plugins
    from calstation.engine.initial import initial_calibration
    from calstation.engine.metrics import axis_errors
    from calstation.recipes import load_recipe
    from calstation.recordings.reader import read_recording

    rc = load_recipe(recipe_path).recipe
    _preload()
    for name in ENGINE_MODULES:
        importlib.import_module(name)
    static = read_recording(out / "static.mcap")
    start = initial_calibration(static, rc.fixtures.static_target, rc.calibration.initial).H
    spin, cube = (turned(read_recording(out / f"{k}.mcap")) for k in ("spin", "cube"))
    strategy = plugins.strategy(rc.calibration.strategy)
    fixture = spin if strategy.fixture == "spin_target" else cube
    fine = strategy.run_prepared(fixture.prepared, start, rc)
    stage_s, checked = _timed(lambda: with_cube(rc, strategy, fine, cube, spin=spin))
    combined, check = checked.result, checked.check
    assert cube.recording is not None
    turns = cube.turns()
    judged_s, _ = _timed(lambda: judged(combined, rc, turns))
    made = stage_made_while_turning(rc, strategy.fixture, fine)
    truth = cube.recording.truth
    found: dict[str, Any] = {
        "seconds": judged_s if made else stage_s + judged_s, "stage_s": stage_s,
        "made_while_turning": made,
        "strategy": combined.strategy, "failure": checked.ry_failure,
        "edge_error_mm": check.edge_error * 1e3, "passed": bool(check.passed),
        "twist_deg": check.twist_deg, "range": combined.range_fields(), "accuracy": None,
        "peak_mb": peak_mb(),
    }
    if truth is not None:
        e = axis_errors(combined.H, truth)
        found["accuracy"] = {"offset_mm": e["axis_offset_m"] * 1e3,
                             "direction_deg": math.degrees(e["axis_angle_rad"]),
                             "ry_deg": math.degrees(e["ry_error"])}
    sensor = json.loads((out / "truth.json").read_text()).get("sensor", {}).get("range", {})
    found["range_truth"] = {"range_offset": sensor.get("offset"),
                            "incidence_bias": sensor.get("incidence_bias")}
    return found


def stage_made_while_turning(rc: Any, fixture: str, fine: Any) -> bool:
    """Whether this revision's station makes the cube stage in the cube scan's turn fits, while
    the cube turns, and its cube step takes it as it is (``TurnFit.stage``): a spin-target
    strategy with the lidar's range model, on a cube scan that may turn past its revolutions."""
    try:
        from calstation.recipes.validation import most_turns
        from calstation.station import prepared
    except ImportError:  # a revision before either
        return False
    if "stage" not in getattr(prepared.TurnFit, "__dataclass_fields__", {}):
        return False  # a revision before it
    return (fixture == "spin_target" and fine.range_offset is not None
            and most_turns(rc, "cube_scan") > rc.steps.cube_scan.revolutions)


def judged(result: Any, rc: Any, turns: float) -> Any:
    """What the cube step does with the final H after the stage: its predicted error, judged
    against the budget (``calstation.station.steps.cube_scan._budget``)."""
    from calstation.pipeline.judgement import budget_failure, with_prediction

    final, predicted = with_prediction(result, rc, turns=turns)
    return budget_failure(final, predicted, rc, scan="cube_scan", turns=turns)


def _duration(rec: Any) -> float:
    """Seconds the scan took: its first to its last return."""
    return float(rec.t_ns[-1] - rec.t_ns[0]) * 1e-9 if rec.n_points else 0.0


def processing(m: dict[str, Any]) -> dict[str, float]:
    """Processing after the scans (station) and from the files, and their ratios."""
    t = m["t"]
    # the station's cube step holds the cube check (with the range model, the known-size
    # fit and the refits before it)
    after = (t["initial"] + t.get("periodicity after scan", t["periodicity"])
             + t.get(CUBE_STEP, t["cube check"]))
    files = t["read"] + t["initial"] + t["periodicity"] + t["cube check"]
    acq = m["acquisition_s"]
    return {"after scans": after, "from files": files, "acquisition": acq,
            "ratio": after / acq, "ratio from files": files / acq}


def _mark(name: str, value: float) -> str:
    target = TARGETS.get(name)
    if target is None:
        return ""
    unit = "" if name in ("ratio",) else (" MB" if "MB" in name else " s")
    return f"target ≤ {target:g}{unit}: {'PASS' if value <= target else 'MISS'}"


def report(runs: list[dict[str, Any]], label: str = "") -> dict[str, float]:
    """Print the median of each stage with its target and the accuracy; the medians."""
    med = {k: statistics.median(r["t"][k] for r in runs) for k in runs[0]["t"]}
    print(f"\n{label}stage times, median of {len(runs)} (min–max):")
    for name, value in med.items():
        lo = min(r["t"][name] for r in runs)
        hi = max(r["t"][name] for r in runs)
        print(f"  {name:<26} {value:7.3f} s  ({lo:.3f}–{hi:.3f})  {_mark(name, value)}")
    proc = [processing(r) for r in runs]
    ratio = statistics.median(p["ratio"] for p in proc)
    print(f"  processing after the scans {statistics.median(p['after scans'] for p in proc):.2f} s"
          f" for {proc[0]['acquisition']:.2f} s of scans: ratio {ratio:.2f}  "
          f"{_mark('ratio', ratio)}")
    print(f"  everything from the files  {statistics.median(p['from files'] for p in proc):.2f} s:"
          f" ratio {statistics.median(p['ratio from files'] for p in proc):.2f}")
    peak = max(max(v for k, v in r["mem"].items() if k != STATION) for r in runs)
    print(f"  peak memory {peak:.0f} MB  {_mark('peak memory MB', peak)}; after each stage: "
          + ", ".join(f"{k} {v:.0f}" for k, v in runs[-1]["mem"].items()))
    station_peak = max((r["mem"].get(STATION, math.nan) for r in runs), default=math.nan)
    print(f"  peak memory of the station's path {station_peak:.0f} MB  "
          f"{_mark('station peak memory MB', station_peak)}")
    points = runs[0]["points"]
    print(f"  {points['spin']:,} spin-scan points, {points['cube']:,} cube points; "
          f"{runs[0]['iterations']} periodicity iterations")
    _accuracy(runs[-1])
    med["ratio"] = ratio
    med["peak memory MB"] = peak
    med["station peak memory MB"] = station_peak
    return med


def _accuracy(m: dict[str, Any]) -> None:
    print("  accuracy against the simulator's truth:")
    for name, a in m["accuracy"].items():
        print(f"    {name:<22} axis offset {a['offset_mm']:6.3f} mm   direction "
              f"{a['direction_deg']:6.3f}°   ry {a['ry_deg']:+7.3f}°")
    print(f"    cube check (periodicity H): face-fit edge error {m['edge_error_mm']:.3f} mm, "
          f"passed={m['cube_passed']}")
    if "cube_step" in m:
        step = m["cube_step"]
        where = ("made while the cube turned" if step.get("made_while_turning")
                 else "made after the scan")
        print(f"    cube step (spin target + cube, {step['strategy']}; its stage {where}): "
              f"{_range_text(step)}; its cube check: face-fit edge error "
              f"{step['edge_error_mm']:.3f} mm, twist {step['twist_deg']:+.3f}°, "
              f"passed={step['passed']}"
              + (f"; refused: {step['failure']}" if step["failure"] else ""))
    if "large_cube" in m:
        print(f"    cube check of the 0.4 m cube (true H): face-fit edge error "
              f"{m['large_cube']['edge_error_mm']:.3f} mm, passed={m['large_cube']['passed']}")


def _range_text(step: dict[str, Any]) -> str:
    """The cube step's range terms against the simulator's truth (mm, with their σ)."""
    parts = []
    for name, label in (("range_offset", "range offset"), ("incidence_bias", "incidence bias")):
        value, truth = step["range"].get(name), step["range_truth"].get(name)
        if value is None:
            continue
        sigma = step["range"].get(f"sigma_{name}") or math.nan
        error = "" if truth is None else f" (error {(value - truth) * 1e3:+.3f} mm)"
        parts.append(f"{label} {value * 1e3:+.3f} ± {sigma * 1e3:.3f} mm{error}")
    return ", ".join(parts) or "no range model"


def _recipe_of(args: argparse.Namespace, rev_dir: Path | None) -> Path:
    """The recipe a measurement of this revision (``rev_dir`` None) or of the compared one
    reads: ``--their-recipe`` for the compared one when given, else ``--recipe``."""
    return Path(args.recipe if rev_dir is None else (args.their_recipe or args.recipe))


def _child(rev_dir: Path | None, args: argparse.Namespace, out: Path) -> dict[str, Any]:
    """One measurement in a fresh process, of this revision or of the one in ``rev_dir``."""
    env = dict(ENVIRONMENT)
    script = Path(__file__).resolve()
    if rev_dir is not None:
        # that revision's own benchmark, package and plugins (their import paths differ)
        plugins = sorted(str(p.parent) for p in rev_dir.glob("plugins/*/pyproject.toml"))
        env["PYTHONPATH"] = os.pathsep.join([str(rev_dir), *plugins, env.get("PYTHONPATH", "")])
        script = rev_dir / "benchmarks" / "calibration.py"
    found: dict[str, Any] = {}
    recipe = _recipe_of(args, rev_dir)
    for mode in ("--json", "--json-station"):
        cmd = [sys.executable, str(script), mode, "--out", str(out),
               "--recipe", str(recipe)] + ([] if args.shape else ["--no-shape"])
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=rev_dir or REPO)
        if proc.returncode != 0:
            raise SystemExit(f"measurement failed ({rev_dir or 'this revision'}):\n"
                             f"{proc.stderr[-2000:]}")
        part = dict(json.loads(proc.stdout.strip().splitlines()[-1]))
        if mode == "--json":
            found = part
            large = _large_cube(env, rev_dir, args, out)
            found["t"]["cube check, 0.4 m cube"] = large["seconds"]
            found["large_cube"] = large
            step = _own_process(env, rev_dir, args, out, "--json-cube-step")
            if step:
                found["t"][CUBE_STEP] = step["seconds"]
                # the stage itself, after the scan or while the cube turns (made_while_turning)
                found["t"][CUBE_STAGE] = step.get("stage_s", step["seconds"])
                found["cube_step"] = step
                if step["accuracy"] is not None:
                    found["accuracy"]["spin target + cube"] = step["accuracy"]
        elif part:
            found["t"].update(part["t"])
            found["mem"][STATION] = part["peak_mb"]
            if part["accuracy"] is not None:
                found["accuracy"]["periodicity (station)"] = part["accuracy"]
    return found


def _large_cube(env: dict[str, str], rev_dir: Path | None, args: argparse.Namespace,
                out: Path) -> dict[str, Any]:
    """The cube check of the 0.4 m cube's recording (simulated beside ``out``) in a process of
    its own (:func:`_own_process`)."""
    return _own_process(env, rev_dir, args, out.parent / f"{out.name}-large-cube",
                        "--json-large")


def _own_process(env: dict[str, str], rev_dir: Path | None, args: argparse.Namespace,
                 out: Path, mode: str) -> dict[str, Any]:
    """One of this script's measurements (``mode``: ``--json-large``, ``--json-cube-step``) on
    the recordings in ``out``, in a process of its own, with the engine of this revision or of
    the one in ``rev_dir`` (this script's measurement: the engine's interface is the same)."""
    recipe = _recipe_of(args, rev_dir)
    cmd = [sys.executable, str(Path(__file__).resolve()), mode, "--out", str(out),
           "--recipe", str(recipe)]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=rev_dir or REPO)
    if proc.returncode != 0:
        raise SystemExit(f"{mode} measurement failed ({rev_dir or 'this revision'}):\n"
                         f"{proc.stderr[-2000:]}")
    return dict(json.loads(proc.stdout.strip().splitlines()[-1]))


def measure_large_cube(recipe_path: Path, out: Path) -> dict[str, Any]:
    """Seconds of the cube check of the 0.4 m cube under the true H (its edge error beside)."""
    from calstation.engine.cube import check_cube
    from calstation.recipes import load_recipe
    from calstation.recordings.reader import read_recording

    rc = load_recipe(recipe_path).recipe
    _preload()
    rec = read_recording(out / "cube.mcap")
    qa_cube = rc.fixtures.qa_cube.model_copy(update={"edge": 0.4, "offset": (0.0, 0.0)})
    assert rec.truth is not None
    t, check = _timed(lambda: check_cube(rec, rec.truth, qa_cube, rc.qa,
                                         platter_radius=rc.fixtures.platter.radius))
    return {"seconds": t, "edge_error_mm": check.edge_error * 1e3, "passed": bool(check.passed)}


def station_waits(folder: Path) -> None:
    """The wait at the station over the capability sweep's runs in ``folder`` (its
    ``station.jsonl``): median and p95 of the fine calibration ready after the spin scan, of the
    result ready after the last scan, and of the cube check."""
    import numpy as np

    log = folder / "station.jsonl"
    rows = [json.loads(line) for line in log.read_text().splitlines() if line.strip()]
    print(f"\nthe wait at the station over {len(rows)} simulated station runs ({log}):")
    for key, label, target in (
            ("fit_s", "fine calibration ready after the spin scan", (0.3, 1.0)),
            ("cube_after_scan_s", "result ready after the last scan", None),
            ("cube_check_s", "cube check", None)):
        values = [r[key] for r in rows if r.get(key) is not None]
        if not values:
            print(f"  {label:<44} —")
            continue
        med, p95 = float(np.median(values)), float(np.percentile(values, 95))
        mark = "" if target is None else (
            f"  target ≤ {target[0]:g} / ≤ {target[1]:g} s: "
            f"{'PASS' if med <= target[0] and p95 <= target[1] else 'MISS'}")
        print(f"  {label:<44} median {med:6.3f} s, p95 {p95:6.3f} s, max {max(values):6.3f} s "
              f"({len(values)} runs){mark}")


def compare(args: argparse.Namespace, out: Path) -> None:
    """Measure this revision and ``args.compare`` side by side, alternating."""
    rev = subprocess.run(["git", "rev-parse", "--short", args.compare], cwd=REPO,
                         capture_output=True, text=True, check=True).stdout.strip()
    tmp = Path(tempfile.mkdtemp(prefix="calstation-rev-"))
    subprocess.run(["git", "worktree", "add", "--detach", str(tmp), rev], cwd=REPO,
                   check=True, capture_output=True)
    try:
        mine: list[dict[str, Any]] = []
        theirs: list[dict[str, Any]] = []
        for i in range(args.repeat):
            print(f"round {i + 1}/{args.repeat}: this revision, then {rev}", flush=True)
            mine.append(_child(None, args, out))
            theirs.append(_child(tmp, args, out))
    finally:
        subprocess.run(["git", "worktree", "remove", "--force", str(tmp)], cwd=REPO,
                       capture_output=True)
    a = report(mine, "this revision — ")
    b = report(theirs, f"{rev} — ")
    print(f"\n{'stage':<26} {'this':>9} {rev:>9}  {rev} ÷ this")
    for name in a:
        if name in b and a[name] > 0:
            print(f"{name:<26} {a[name]:9.3f} {b[name]:9.3f}  {b[name] / a[name]:6.2f}")
    _same_estimates(mine, theirs, rev)


def _same_estimates(mine: list[dict[str, Any]], theirs: list[dict[str, Any]], rev: str) -> None:
    """Whether the two revisions' estimates are the same, to the last bit of every accuracy
    figure (each H's axis offset, direction and ry against the truth) and of the cube's edge
    error, round by round."""
    print(f"\nestimates, this revision against {rev} (every round, every stage):")
    for name in mine[0]["accuracy"]:
        diffs = [max(abs(m["accuracy"][name][k] - t["accuracy"][name][k]) for k in
                     ("offset_mm", "direction_deg", "ry_deg"))
                 for m, t in zip(mine, theirs, strict=True) if name in t["accuracy"]]
        if not diffs:
            print(f"  {name:<22} not measured by {rev}")
            continue
        print(f"  {name:<22} " + ("identical" if max(diffs) == 0 else
                                  f"differ: up to {max(diffs):.3g} (mm or °)"))
    edge = max(abs(m["edge_error_mm"] - t["edge_error_mm"])
               for m, t in zip(mine, theirs, strict=True))
    print(f"  {'cube edge error':<22} " + ("identical" if edge == 0 else
                                          f"differs: up to {edge:.3g} mm"))
    steps = [(m["cube_step"], t["cube_step"]) for m, t in zip(mine, theirs, strict=True)
             if "cube_step" in m and "cube_step" in t]
    if steps:
        keys = ("range", "edge_error_mm", "twist_deg", "failure")
        # as JSON: a σ not estimated (NaN) is the same as another
        same = all(json.dumps([a[k] for k in keys]) == json.dumps([b[k] for k in keys])
                   for a, b in steps)
        texts = [(_range_text(a), _range_text(b)) for a, b in steps]
        if same:
            said = "identical"
        elif all(x == y for x, y in texts):
            said = (f"differ: up to {_range_difference(steps) * 1e3:.3g} mm in a range term "
                    "or its σ, the same to the printed digits")
        else:
            said = "differ: " + "; ".join(f"{x} against {y}" for x, y in texts)
        print(f"  {'cube step range terms':<22} {said}")


def _range_difference(steps: list[tuple[dict[str, Any], dict[str, Any]]]) -> float:
    """The largest difference (m) between two revisions' cube-step range terms or their σ."""
    out = 0.0
    for a, b in steps:
        for name in ("range_offset", "incidence_bias"):
            for key in (name, f"sigma_{name}"):
                x, y = a["range"].get(key), b["range"].get(key)
                if x is not None and y is not None and math.isfinite(x - y):
                    out = max(out, abs(x - y))
    return out


def scaling(args: argparse.Namespace, base: Path) -> None:
    """Periodicity time, memory and accuracy against the spin scan's size."""
    print("\nscaling with the spin scan's size (periodicity from the recording, and the "
          "station's wait after the scan):")
    for millions, (rate, rpm) in SCALING.items():
        out = base / f"scaling-{millions:g}M"
        simulate(args.recipe, out, args.seed, args.range_m, args.pitch,
                 {"simulation.lidar.line_rate_hz": rate, "steps.spin_scan.rpm": rpm})
        m = _child(None, argparse.Namespace(**{**vars(args), "shape": False}), out)
        a = m["accuracy"]["periodicity"]
        print(f"  {m['points']['spin'] / 1e6:4.2f} M points: periodicity "
              f"{m['t']['periodicity']:6.2f} s, after the scan "
              f"{m['t'].get('periodicity after scan', math.nan):6.2f} s, peak "
              f"{max(m['mem'].values()):5.0f} MB; axis offset {a['offset_mm']:.3f} mm, "
              f"direction {a['direction_deg']:.3f}°, ry {a['ry_deg']:+.3f}°", flush=True)


def _revision() -> str:
    rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO,
                         capture_output=True, text=True).stdout.strip()
    dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=REPO,
                           capture_output=True, text=True).stdout.strip()
    return rev + ("+dirty" if dirty else "")


def _load() -> str:
    return "load average " + " ".join(f"{x:.2f}" for x in os.getloadavg())


def main() -> None:
    """Run the benchmark and print its figures."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--recipe", type=Path, default=REPO / "recipes/sim-periodicity.yaml")
    ap.add_argument("--range", type=float, default=1.25, dest="range_m")
    ap.add_argument("--pitch", type=float, default=45.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", type=Path, default=None, help="folder for (or with) the recordings")
    ap.add_argument("--scaling", action="store_true", help="also 0.5, 1, 2 and 4 M points")
    ap.add_argument("--compare", metavar="REV", help="measure this git revision side by side")
    ap.add_argument("--their-recipe", type=Path, default=None, metavar="R",
                    help="with --compare: the recipe REV reads, where its schema differs "
                         "(the same scene and settings in REV's words); default --recipe")
    ap.add_argument("--no-shape", dest="shape", action="store_false", help="skip shape")
    ap.add_argument("--json", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--json-station", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--json-large", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--json-cube-step", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--station-runs", type=Path, metavar="DIR", default=None,
                    help="also the wait at the station over the capability sweep's runs in DIR")
    args = ap.parse_args()
    # absolute: the measurements of another revision run in its own worktree
    out = (args.out or Path(tempfile.mkdtemp(prefix="calstation-bench-"))).resolve()
    args.recipe = args.recipe.resolve()
    if args.their_recipe is not None:
        args.their_recipe = args.their_recipe.resolve()
    if args.json:  # one measurement for a parent process
        print(json.dumps(measure(args.recipe, out, args.shape)))
        return
    if args.json_station:
        print(json.dumps(measure_station(args.recipe, out)))
        return
    if args.json_large:
        print(json.dumps(measure_large_cube(args.recipe, out)))
        return
    if args.json_cube_step:
        print(json.dumps(measure_cube_step(args.recipe, out)))
        return
    simulate(args.recipe, out, args.seed, args.range_m, args.pitch)
    simulate(args.recipe, out.parent / f"{out.name}-large-cube", args.seed, args.range_m,
             args.pitch, LARGE_CUBE)
    print(f"calstation {_revision()}; scenario: range {args.range_m} m, pitch {args.pitch}°, "
          f"seed {args.seed}; {os.cpu_count()} CPUs, {_load()}", flush=True)
    if args.compare:
        compare(args, out)
    else:
        report([_child(None, args, out) for _ in range(args.repeat)])
    if args.station_runs is not None:
        station_waits(args.station_runs)
    if args.scaling:
        scaling(args, out.parent if args.out else out)
    print(f"\nend: {_load()}")


if __name__ == "__main__":
    main()
