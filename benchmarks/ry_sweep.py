"""The capability sweep of docs/algorithms.md: the station's calibration under noise, background,
placement and line-rate conditions the default simulator does not produce, against the truth.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/ry_sweep.py station [--runs 72] [--jobs 2]
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/ry_sweep.py turns [--scenes 24] [--jobs 2]
    .venv/bin/python benchmarks/ry_sweep.py table --out DIR
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/ry_sweep.py plan --out DIR

``station``: each run is a whole simulated ``calstation run`` of recipes/sim-periodicity.yaml
(``--recipe`` another, e.g. sim-shape.yaml) with one combination of range noise (0.5, 1, 2 mm),
line rate (180, 1000 lines/s), background (on, off) and spin-target placement (centred, 60 mm
off), the scenario cycling through the paper's nine and 0.9 m / 40°, a new seed per run. The
station decides it exactly as it decides a run on the shop floor: turn by turn until the
accuracy budget holds (up to ``max_revolutions``), the cube's faces combined into ry, the budget
on the final calibration. The sweep prints, per noise level, how many runs were accepted, the
accepted runs' axis direction and offset errors, the turns taken, the scanning and computing
time, the 3σ coverage of every parameter (accepted and refused estimates alike), and whether the
predicted reconstruction error covered the true distortion over the work volume.

``turns``: the σ coverage at fixed turns, for both strategies. Each scene is simulated once with
long spin and cube scans (8 turns at 180 lines/s, 4 at 1000 lines/s: 25 million points is the
simulator's limit); the periodicity strategy (alone, and with the cube's faces) and the shape
strategy fine-tune on the first 1, 2, 4 and 8 turns, from the initial calibration, and each
estimate's error is compared with its σ.

``plan``: ``calstation plan`` of the recipe at each range noise and line rate (2 seeds, 1 and 2
turns, the recipe's own placement), against the median σ_ry the ``turns`` sweep measured at the
same noise, line rate and turns (run ``turns`` first): the station designer's prediction checked
against the sweep.
"""

from __future__ import annotations

import argparse
import copy
import itertools
import json
import math
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from calstation.recipes import LoadedRecipe, parse_recipe

REPO = Path(__file__).resolve().parents[1]
SCENARIOS = [(r, p) for r in (1.0, 1.25, 1.5) for p in (30.0, 45.0, 60.0)] + [(0.9, 40.0)]
CONDITIONS = list(itertools.product((0.0005, 0.001, 0.002), (1000.0, 180.0), (False, True),
                                    (0.0, 0.06)))
"""(range noise m, line rate lines/s, background, spin-target offset m)"""
PARAMS = ("tx", "tz", "ry", "rz")
SPIN_RPM = 20.0
"""The spin scan's platter speed in recipes/sim-periodicity.yaml (the time a scan takes)."""
TURNS = (1, 2, 4, 8)


def sim_recipe(noise: float, background: bool, offset: float, rate: float,
               scenario: tuple[float, float], seed: int,
               recipe: Path = REPO / "recipes/sim-periodicity.yaml",
               steps: dict[str, Any] | None = None) -> LoadedRecipe:
    """``recipe`` with these simulation conditions (and ``steps`` merged into its steps)."""
    data = copy.deepcopy(yaml.safe_load(recipe.read_text()))
    sim = data["simulation"]
    sim.update(seed=seed, truth={"range": scenario[0], "pitch_deg": scenario[1]},
               background={"enabled": background})
    sim["lidar"].update(range_noise=noise, line_rate_hz=rate)
    data["fixtures"]["spin_target"]["offset"] = [offset, 0.0]
    for name, values in (steps or {}).items():
        data["steps"].setdefault(name, {}).update(values)
    text = yaml.safe_dump(data)
    return LoadedRecipe(parse_recipe(text, f"simulated run, seed {seed}"), None, text)


def _condition(k: int) -> dict[str, Any]:
    noise, rate, background, offset = CONDITIONS[k % len(CONDITIONS)]
    return {"noise": noise, "line_rate": rate, "background": background, "offset": offset,
            "scenario": SCENARIOS[k % len(SCENARIOS)]}


# --- the station, turn by turn -----------------------------------------------------------------
class _Quiet:
    """An unattended operator that keeps nothing on the console."""

    unattended = True

    def info(self, message: str) -> None:
        pass

    warn = info

    def confirm_fixture(self, fixture: str, description: str) -> bool:
        return True

    def on_failure(self, step: str, error: str, attempt: int) -> str:
        return "abort"

    @contextmanager
    def progress(self, title: str) -> Iterator[Callable[[str, float], None]]:
        yield lambda phase, fraction: None

    def summary(self, summary: dict[str, Any]) -> None:
        pass


def station_run(k: int, out: Path, recipe: Path) -> dict[str, Any]:
    """Run ``k`` as a whole simulated station run; its row (SI units)."""
    cond = _condition(k)
    loaded = sim_recipe(cond["noise"], cond["background"], cond["offset"], cond["line_rate"],
                        cond["scenario"], 100 + k, recipe)
    row = unattended_run(loaded, out / f"run{k}", _station_row)
    row.update(k=k, **cond)
    return row


def unattended_run(
    loaded: LoadedRecipe, folder: Path,
    row_of: Callable[[Any, int, str, LoadedRecipe], dict[str, Any]],
) -> dict[str, Any]:
    """``loaded`` run as the station runs it, unattended, with its own database in ``folder``:
    ``row_of(db, run_id, status, loaded)`` with the run's wall time (``wall_s``); the
    recordings are deleted after it (a sweep keeps its rows, not its scans)."""
    from calstation.station.runs import start_run
    from calstation.storage.db import open_database

    folder.mkdir(parents=True, exist_ok=True)
    db = open_database(f"sqlite:///{folder / 'run.db'}")
    t0 = time.perf_counter()
    try:
        run_id, status = start_run(loaded, db, _Quiet(), operator="sweep", data_dir=folder)
        row = row_of(db, run_id, status, loaded)
    finally:
        db.dispose()
    row["wall_s"] = time.perf_counter() - t0
    for path in folder.rglob("*.mcap"):
        path.unlink()
    return row


def _station_row(db: Any, run_id: int, status: str, loaded: LoadedRecipe) -> dict[str, Any]:
    """What the station decided, its final estimate (accepted, or the one it refused), the
    truth, the turns and times."""
    from calstation.engine.accuracy import true_distortion
    from calstation.engine.frames import Extrinsics
    from calstation.engine.metrics import axis_errors
    from calstation.engine.rangemodel import RangeModel
    from calstation.recordings.reader import read_recording
    from calstation.storage.db import Artifact, Calibration, Step

    recipe = loaded.recipe
    with db.session() as s:
        steps = {st.name: st for st in s.query(Step).filter_by(run_id=run_id).order_by(Step.id)}
        cals = s.query(Calibration).filter_by(run_id=run_id).order_by(Calibration.id).all()
        spin = s.query(Artifact).filter_by(run_id=run_id, kind="spin").first()
        recording = read_recording(spin.path) if spin is not None else None
        truth = recording.truth if recording is not None else None
        meta = recording.metadata.get("truth", {}) if recording is not None else {}
        final = next((c for c in cals if c.accepted), None) or next(
            (c for c in reversed(cals) if c.stage == "fine"), None)
        estimate = None
        if final is not None:
            estimate = {"H": final.params(), "sigma": final.sigmas(),
                        "predicted_error_m": final.predicted_error_m, "strategy": final.strategy,
                        "range_offset": final.range_offset,
                        "sigma_range_offset": final.sigma_range_offset,
                        "range_scale": final.range_scale}
        elif "fine_tune" in steps and (steps["fine_tune"].result or {}).get("refused"):
            refused = steps["fine_tune"].result["refused"]
            estimate = {"H": refused["H"], "sigma": refused["sigma"],
                        "predicted_error_m": refused.get("predicted_error_m"),
                        "strategy": "refused"}
        spin_result = (steps.get("spin_scan").result or {}) if "spin_scan" in steps else {}
        fine_result = (steps.get("fine_tune").result or {}) if "fine_tune" in steps else {}
        cube_result = (steps.get("cube_scan").result or {}) if "cube_scan" in steps else {}
        failed = [st.error for st in steps.values() if st.status == "failed" and st.error]
    row: dict[str, Any] = {
        "status": status, "accepted": status == "passed", "failure": failed[:1],
        "turn_by_turn": spin_result.get("turn_by_turn"), "turns": fine_result.get("turns"),
        "fit_s": fine_result.get("after_scan_s"),
        "cube_after_scan_s": cube_result.get("after_scan_s"),
        "cube_check_s": cube_result.get("cube_check_s"),
    }
    if estimate is not None and truth is not None:
        H = Extrinsics.from_dict(estimate["H"])
        accuracy = recipe.calibration.accuracy
        row["estimate"] = estimate
        row["err"] = axis_errors(H, truth)
        # the lidar as simulated, and as the estimate reconstructs with it (its range model)
        truth_range = RangeModel(float(meta.get("range_offset", 0.0)),
                                 float(meta.get("range_scale", 0.0)))
        row["true_range_offset"] = truth_range.offset
        row["true_distortion_m"] = true_distortion(
            H, truth, radius=accuracy.work_radius(recipe.fixtures.platter),
            height=accuracy.height, estimate_range=RangeModel(
                estimate.get("range_offset") or 0.0, estimate.get("range_scale") or 0.0),
            truth_range=truth_range)["max_m"]
    return row


# --- fixed turns, both strategies --------------------------------------------------------------
def turns_scene(k: int, out: Path) -> dict[str, Any]:
    """Scene ``k`` simulated once with long scans; every strategy on the first 1, 2, 4, 8 turns."""
    from calstation_sim import simulate_run

    from calstation.engine.initial import initial_calibration
    from calstation.recordings.reader import read_recording

    cond = _condition(k)
    most = 8 if cond["line_rate"] < 500 else 4
    long = {"revolutions": most + 0.05, "max_revolutions": most + 0.05}
    loaded = sim_recipe(cond["noise"], cond["background"], cond["offset"], cond["line_rate"],
                        cond["scenario"], 900 + k,
                        steps={"spin_scan": long, "cube_scan": long})
    recipe = loaded.recipe
    paths = simulate_run(loaded, out / f"scene{k}", progress=False)
    try:
        static = read_recording(paths["static"])
        truth = static.truth
        assert truth is not None
        start = initial_calibration(static, recipe.fixtures.static_target,
                                    recipe.calibration.initial).H
        spin, cube = read_recording(paths["spin"]), read_recording(paths["cube"])
        rows = [_at_turns(recipe, spin, cube, start, truth, n) for n in TURNS if n <= most]
    finally:
        for name in paths.values():
            Path(name).unlink(missing_ok=True)
    return {"k": k, **cond, "estimates": [e for r in rows for e in r]}


def _at_turns(recipe: Any, spin: Any, cube: Any, start: Any, truth: Any,
              n: int) -> list[dict[str, Any]]:
    """The periodicity (alone, and with the cube's faces) and shape estimates on n turns."""
    from calstation.engine.metrics import axis_errors
    from calstation.errors import CalstationError
    from calstation.pipeline import turned
    from calstation.pipeline.stages import with_cube
    from calstation.plugins.cost_strategies import PeriodicityStrategy, ShapeStrategy, run_strategy

    out = []

    def record(method: str, fit: Callable[[], Any]) -> Any:
        t0 = time.perf_counter()
        try:
            result = fit()
        except CalstationError as exc:
            out.append({"method": method, "turns": n, "error": str(exc)})
            return None
        out.append({"method": method, "turns": n, "sigma": dict(result.sigma),
                    "err": axis_errors(result.H, truth), "s": time.perf_counter() - t0})
        return result

    # each scan's returns prepared once, for every estimate made from it
    spin_n, cube_n = turned(spin.first_turns(n)), turned(cube.first_turns(n))
    fine = record("periodicity", lambda: run_strategy(
        PeriodicityStrategy(), spin_n.recording, start, recipe, prepared=spin_n.prepared)[0])
    if fine is not None:
        record("periodicity+cube",
               lambda: with_cube(recipe, PeriodicityStrategy(), fine, cube_n).result)
    record("shape", lambda: run_strategy(ShapeStrategy(), cube_n.recording, start, recipe,
                                         prepared=cube_n.prepared)[0])
    return out


# --- the tables --------------------------------------------------------------------------------
def _deg(x: float) -> float:
    return math.degrees(x)


def _stats(values: list[float], unit: str, scale: float) -> str:
    if not values:
        return "—"
    v = np.asarray(values) * scale
    return (f"median {np.median(v):.3f}{unit}, p95 {np.percentile(v, 95):.3f}{unit}, "
            f"max {v.max():.3f}{unit}")


def _covered(est: dict[str, Any], p: str) -> bool | None:
    sigma = est["sigma"].get(p)
    if sigma is None or not math.isfinite(sigma):
        return None
    return abs(est["err"][f"{p}_error"]) <= 3 * sigma


def station_table(rows: list[dict[str, Any]]) -> None:
    """Per noise level: acceptance, accuracy of the accepted, turns, times, coverage."""
    for noise in sorted({r["noise"] for r in rows}):
        sel = [r for r in rows if r["noise"] == noise]
        acc = [r for r in sel if r["accepted"] and "err" in r]
        with_est = [r for r in sel if "err" in r]
        turns = [r["turns"] for r in sel if r.get("turns")]
        print(f"{noise * 1e3:.1f} mm: {len(sel)} runs, {len(acc)} accepted "
              f"({100 * len(acc) / max(len(sel), 1):.0f} %)")
        directions = [r["err"]["axis_angle_rad"] for r in acc]
        offsets = [r["err"]["axis_offset_m"] for r in acc]
        print(f"  accepted axis direction: {_stats(directions, '°', math.degrees(1.0))}")
        print(f"  accepted axis offset: {_stats(offsets, ' mm', 1e3)}")
        print(f"  turns: mean {np.mean(turns) if turns else math.nan:.2f}, max "
              f"{max(turns) if turns else '—'}; wall time per run (simulation included): "
              f"mean {np.mean([r['wall_s'] for r in sel]):.0f} s")
        scanned = [(r.get("turn_by_turn") or {}).get("whole_turns", r.get("turns")) for r in sel]
        scanned = [t for t in scanned if t]
        print(f"  spin scan on the station (whole turns at {SPIN_RPM:g} rpm): mean "
              f"{np.mean(scanned) * 60 / SPIN_RPM if scanned else math.nan:.1f} s")
        for key, what in (("fit_s", "fine calibration ready after the spin scan ended"),
                          ("cube_after_scan_s", "result ready after the last scan ended"),
                          ("cube_check_s", "cube check")):
            ready = [r[key] for r in sel if r.get(key) is not None]
            print(f"  {what}: median {np.median(ready) if ready else math.nan:.2f} s, p95 "
                  f"{np.percentile(ready, 95) if ready else math.nan:.2f} s, max "
                  f"{max(ready) if ready else math.nan:.2f} s")
        cover = []
        for p in ("tx", "ty", "tz", "ry", "rz"):  # ty: estimated with a range model only
            flags = [_covered(r["estimate"] | {"err": r["err"]}, p) for r in with_est]
            flags = [f for f in flags if f is not None]
            if flags:
                cover.append(f"{p} {sum(flags)}/{len(flags)}")
        offsets_b = [r for r in with_est if r["estimate"].get("sigma_range_offset")]
        if offsets_b:  # the lidar's range offset against the simulated one
            held = sum(abs(r["estimate"]["range_offset"] - r.get("true_range_offset", 0.0))
                       <= 3 * r["estimate"]["sigma_range_offset"] for r in offsets_b)
            cover.append(f"range offset {held}/{len(offsets_b)}")
        predicted = [(r["true_distortion_m"], r["estimate"]["predicted_error_m"])
                     for r in with_est if r["estimate"].get("predicted_error_m") is not None]
        print(f"  |error| ≤ 3σ (accepted and refused): {', '.join(cover)}; predicted error ≥ "
              f"true distortion: {sum(t <= p for t, p in predicted)}/{len(predicted)}")
        for r in sel:
            if not r["accepted"]:
                print(f"    refused run {r['k']}: {str(r['failure'][:1])[:300]}")


def turns_table(rows: list[dict[str, Any]]) -> None:
    """Per strategy and number of turns: σ and error of ry, and the 3σ coverage."""
    estimates = [e | {"noise": r["noise"], "rate": r["line_rate"]} for r in rows
                 for e in r["estimates"]]
    for method in ("periodicity", "periodicity+cube", "shape"):
        for n in TURNS:
            sel = [e for e in estimates if e["method"] == method and e["turns"] == n]
            ok = [e for e in sel if "err" in e]
            if not sel:
                continue
            cover = []
            for p in PARAMS:
                flags = [f for f in (_covered(e, p) for e in ok) if f is not None]
                cover.append(f"{p} {sum(flags)}/{len(flags)}")
            ry = [abs(e["err"]["ry_error"]) for e in ok]
            sry = [e["sigma"]["ry"] for e in ok if math.isfinite(e["sigma"].get("ry", math.nan))]
            off = [e["err"]["axis_offset_m"] for e in ok]
            print(f"{method:17} {n} turns: {len(ok)}/{len(sel)} fitted; |ry error| "
                  f"{_stats(ry, '°', math.degrees(1.0))}; σ_ry median "
                  f"{math.degrees(float(np.median(sry))) if sry else math.nan:.3f}°; axis "
                  f"offset {_stats(off, ' mm', 1e3)}; ≤ 3σ: {', '.join(cover)}")


def plan_check(out: Path, recipe: Path) -> None:
    """``calstation plan`` at each noise and line rate against the ``turns`` sweep's σ_ry."""
    from calstation.bench.plan import plan

    log = out / "turns.jsonl"
    if not log.exists():
        raise SystemExit(f"{log} does not exist: run the turns sweep first")
    rows = [json.loads(line) for line in log.read_text().splitlines()]
    with (out / "plan.jsonl").open("a") as f:
        for noise, rate in itertools.product((0.0005, 0.001, 0.002), (180.0, 1000.0)):
            base = yaml.safe_load(recipe.read_text())["simulation"]
            loaded = sim_recipe(noise, base.get("background", {}).get("enabled", True),
                                yaml.safe_load(recipe.read_text())["fixtures"]["spin_target"]
                                .get("offset", [0.0, 0.0])[0], rate,
                                (base["truth"]["range"], base["truth"]["pitch_deg"]),
                                base.get("seed", 0), recipe)
            designed = plan(loaded, seeds=2, turns=2, alternatives=False)["designs"][0]
            for at in designed["by_turns"]:
                n = at["turns"]
                measured = [e["sigma"]["ry"] for r in rows for e in r["estimates"]
                            if math.isclose(r["noise"], noise) and r["line_rate"] == rate
                            and e["method"] == "periodicity" and e["turns"] == n and "err" in e]
                sweep = float(np.median(measured)) if measured else math.nan
                ratio = at["sigma"]["ry"] / sweep
                row = {"noise": noise, "line_rate": rate, "turns": n,
                       "plan_sigma_ry": at["sigma"]["ry"], "sweep_sigma_ry": sweep,
                       "sweep_estimates": len(measured), "ratio": ratio}
                f.write(json.dumps(row) + "\n")
                print(f"{noise * 1e3:.1f} mm, {rate:.0f} lines/s, {n} turn(s): plan σ_ry "
                      f"{_deg(at['sigma']['ry']):.3f}°, sweep median {_deg(sweep):.3f}° over "
                      f"{len(measured)} scenes: ratio {ratio:.2f}"
                      f"{'' if 1 / 1.5 <= ratio <= 1.5 else '  (beyond 1.5×)'}", flush=True)


def run_all(run: Callable[..., dict[str, Any]], jobs: list[tuple[Any, ...]], log: Path,
            workers: int, line: Callable[[dict[str, Any]], str]) -> list[dict[str, Any]]:
    """``run(*job)`` for every job on ``workers`` processes; each row appended to the JSON-lines
    ``log`` and printed as it arrives."""
    rows = []
    with log.open("a") as f, ProcessPoolExecutor(workers) as pool:
        for row in pool.map(run, *zip(*jobs, strict=True)):
            rows.append(row)
            f.write(json.dumps(row, default=float) + "\n")
            f.flush()
            print(line(row), flush=True)
    return rows


def _station_line(r: dict[str, Any]) -> str:
    e = r.get("err")
    head = (f"run {r['k']}: {r['noise'] * 1e3:.1f} mm, {r['line_rate']:.0f} lines/s, background "
            f"{r['background']}, offset {r['offset'] * 1e3:.0f} mm, {r['scenario']}: "
            f"{'accepted' if r['accepted'] else 'refused'} after {r.get('turns')} turns")
    if e:
        head += (f"; direction {_deg(e['axis_angle_rad']):.3f}°, offset "
                 f"{e['axis_offset_m'] * 1e3:.3f} mm, ry {_deg(e['ry_error']):+.3f}° ± "
                 f"{_deg(r['estimate']['sigma']['ry'] or math.nan):.3f}°, predicted "
                 f"{(r['estimate']['predicted_error_m'] or math.nan) * 1e3:.3f} mm, true "
                 f"{r['true_distortion_m'] * 1e3:.3f} mm")
    return head


def _turns_line(r: dict[str, Any]) -> str:
    return (f"scene {r['k']}: {r['noise'] * 1e3:.1f} mm, {r['line_rate']:.0f} lines/s: "
            f"{len(r['estimates'])} estimates")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("mode", choices=("station", "turns", "table", "plan"))
    ap.add_argument("--runs", type=int, default=72, help="station runs (from --first)")
    ap.add_argument("--scenes", type=int, default=24, help="fixed-turn scenes (from --first)")
    ap.add_argument("--first", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=1, help="runs in parallel")
    ap.add_argument("--noise", type=float, default=None,
                    help="only the runs (scenes) of this range noise (m)")
    ap.add_argument("--recipe", type=Path, default=REPO / "recipes/sim-periodicity.yaml")
    ap.add_argument("--out", type=Path, default=REPO / "out" / "capability")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    station_log, turns_log = args.out / "station.jsonl", args.out / "turns.jsonl"
    def picked(count: int) -> list[int]:
        ks = itertools.count(args.first)
        chosen = (k for k in ks if args.noise is None
                  or math.isclose(_condition(k)["noise"], args.noise))
        return list(itertools.islice(chosen, count))

    if args.mode == "station":
        run_all(station_run, [(k, args.out, args.recipe) for k in picked(args.runs)],
                station_log, args.jobs, _station_line)
    elif args.mode == "plan":
        plan_check(args.out, args.recipe)
        return
    elif args.mode == "turns":
        run_all(turns_scene, [(k, args.out) for k in picked(args.scenes)], turns_log, args.jobs,
                _turns_line)
    for log, table in ((station_log, station_table), (turns_log, turns_table)):
        if log.exists():
            print(f"\n{log}:")
            table([json.loads(line) for line in log.read_text().splitlines()])


if __name__ == "__main__":
    main()
