"""The ry sweep of docs/algorithms.md: the station's calibration under noise, background,
placement and line-rate conditions the default simulator does not produce, against the truth.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/ry_sweep.py [--runs 120] [--jobs 2]

Each run simulates recipes/sim-periodicity.yaml with one combination of range noise (0.5, 1,
2 mm), background (on, off), spin-target offset (centred, 60 mm) and line rate (1000, 180
lines/s), the scenario cycling through the paper's nine and 0.9 m / 40°, and decides as the
station does: periodicity fine-tuning from the initial calibration, its σ gate on tx, tz and rz,
the cube check under that H, ry combined with the cube's side-face twist
(:func:`calstation.engine.joint.ry_with_cube`) and the ry gate on the result. It prints, per run and
then per noise level, the axis direction error of the periodicity alone and of the outcome,
what was refused, and the σ coverage (|error| ≤ 3σ) of both. One run takes 30-90 s on one core.
"""

from __future__ import annotations

import argparse
import copy
import itertools
import json
import math
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import yaml

from calstation.engine.initial import initial_calibration
from calstation.engine.metrics import axis_errors
from calstation.engine.observability import sigma_problems
from calstation.plugins.cost_strategies import PeriodicityStrategy, fine_tune_with_cube
from calstation.recipes import LoadedRecipe, parse_recipe
from calstation.recordings.reader import read_recording

REPO = Path(__file__).resolve().parents[1]
SCENARIOS = [(r, p) for r in (1.0, 1.25, 1.5) for p in (30.0, 45.0, 60.0)] + [(0.9, 40.0)]
CONDITIONS = list(itertools.product((0.0005, 0.001, 0.002), (False, True), (0.0, 0.06),
                                    (1000.0, 180.0)))


def sim_recipe(noise: float, background: bool, offset: float, rate: float,
               scenario: tuple[float, float], seed: int) -> LoadedRecipe:
    """recipes/sim-periodicity.yaml with these simulation conditions."""
    data = copy.deepcopy(yaml.safe_load((REPO / "recipes/sim-periodicity.yaml").read_text()))
    sim = data["simulation"]
    sim.update(seed=seed, truth={"range": scenario[0], "pitch_deg": scenario[1]},
               background={"enabled": background})
    sim["lidar"].update(range_noise=noise, line_rate_hz=rate)
    data["fixtures"]["spin_target"]["offset"] = [offset, 0.0]
    text = yaml.safe_dump(data)
    return LoadedRecipe(parse_recipe(text, f"simulated run, seed {seed}"), None, text)


def _recipe(k: int) -> LoadedRecipe:
    return sim_recipe(*CONDITIONS[k % len(CONDITIONS)], SCENARIOS[k % len(SCENARIOS)], 100 + k)


def one(k: int, out: Path) -> dict[str, object]:
    """Simulate run ``k`` and decide it as the station does; its row (SI units)."""
    from calstation_sim import simulate_run

    loaded = _recipe(k)
    recipe = loaded.recipe
    paths = simulate_run(loaded, out / f"run{k}", progress=False)
    static = read_recording(paths["static"])
    truth = static.truth
    assert truth is not None
    initial = initial_calibration(static, recipe.fixtures.static_target, recipe.calibration.initial)
    fine = PeriodicityStrategy().run(read_recording(paths["spin"]), initial.H, recipe)
    limits = recipe.calibration.max_sigma
    refused = sigma_problems(fine, limits, skip=("ry",))
    # the station's cube step: the side faces' twist combined into ry, the ry gate
    outcome, final, failure = fine_tune_with_cube(fine, read_recording(paths["cube"]), recipe)
    joint = outcome.diagnostics.get("joint") if outcome is not fine else None
    if joint is not None:  # the twist measured under the fine-tuned H
        twist = joint["ry_cube"] - joint["ry_spin_target"]
        twist_sigma = joint["sigma_ry_cube"]
    else:
        twist, twist_sigma = math.radians(final.twist_deg), math.radians(final.twist_sigma_deg)
    if failure:
        refused.append(failure)
    for name in paths.values():  # the recordings are large; the rows keep what matters
        Path(name).unlink(missing_ok=True)
    noise, background, offset, rate = CONDITIONS[k % len(CONDITIONS)]
    return {"k": k, "noise": noise, "background": background, "offset": offset,
            "line_rate": rate, "scenario": SCENARIOS[k % len(SCENARIOS)],
            "periodicity": {"err": axis_errors(fine.H, truth), "sigma": fine.sigma},
            "twist": [twist, twist_sigma], "joint": joint is not None,
            "err": axis_errors(outcome.H, truth), "sigma": outcome.sigma, "refused": refused,
            "cube_passed": final.passed, "edge_error": final.edge_error,
            "noise_estimate": fine.diagnostics.get("range_noise_m"),
            "cell": fine.diagnostics.get("final_cell_m")}


def _direction(rows: list[dict], key: str | None = None) -> np.ndarray:
    return np.array([math.degrees((r[key] if key else r)["err"]["axis_angle_rad"])
                     for r in rows])


def _cover(rows: list[dict], key: str | None = None) -> str:
    out = []
    for p in ("tx", "tz", "ry", "rz"):
        n = sum(abs(r_["err"][f"{p}_error"]) <= 3 * r_["sigma"][p]
                for r_ in ((r[key] if key else r) for r in rows))
        out.append(f"{p} {n}/{len(rows)}")
    return ", ".join(out)


def _stats(values: np.ndarray) -> str:
    if not values.size:
        return "—"
    return (f"median {np.median(values):.3f}°, p95 {np.percentile(values, 95):.3f}°, "
            f"max {values.max():.3f}°")


def table(rows: list[dict]) -> None:
    """Per noise level: refusals, direction errors (accepted outcome, periodicity alone) and
    the 3σ coverage of both."""
    for noise in sorted({r["noise"] for r in rows}):
        sel = [r for r in rows if r["noise"] == noise]
        refused = np.array([bool(r["refused"]) for r in sel])
        accepted = _direction(sel)[~refused]
        silent = sum(1 for r in sel if not r["refused"] and any(
            abs(r["err"][f"{p}_error"]) > 3 * r["sigma"][p] for p in ("tx", "tz", "ry", "rz")))
        print(f"{noise * 1e3:.1f} mm: {len(sel)} runs, {int(refused.sum())} refused, "
              f"{sum(r['joint'] for r in sel)} combined with the cube, {silent} accepted beyond "
              f"3σ\n  accepted direction error: {_stats(accepted)}\n  periodicity alone: "
              f"{_stats(_direction(sel, 'periodicity'))}\n  |error| ≤ 3σ, outcome: "
              f"{_cover(sel)}\n  |error| ≤ 3σ, periodicity: {_cover(sel, 'periodicity')}")
    refused = sum(bool(r["refused"]) for r in rows)
    print(f"all: {len(rows)} runs, {refused} refused; |error| ≤ 3σ, outcome: {_cover(rows)}; "
          f"periodicity: {_cover(rows, 'periodicity')}")


def _line(row: dict) -> str:
    e, p = row["err"], row["periodicity"]["err"]
    return (f"run {row['k']}: {row['noise'] * 1e3:.1f} mm, background {row['background']}, "
            f"offset {row['offset'] * 1e3:.0f} mm, {row['line_rate']:.0f} lines/s, "
            f"{row['scenario']}: periodicity direction "
            f"{math.degrees(p['axis_angle_rad']):.3f}°, ry {math.degrees(p['ry_error']):+.3f}° ± "
            f"{math.degrees(row['periodicity']['sigma']['ry']):.3f}°; twist "
            f"{math.degrees(row['twist'][0]):+.3f}° ± {math.degrees(row['twist'][1]):.3f}°; "
            f"outcome direction {math.degrees(e['axis_angle_rad']):.3f}°, ry "
            f"{math.degrees(e['ry_error']):+.3f}° ± {math.degrees(row['sigma']['ry']):.3f}°"
            f"{' (combined)' if row['joint'] else ''}"
            f"{'; refused: ' + row['refused'][0] if row['refused'] else ''}")


def run_all(run: Callable[..., dict], jobs: list[tuple], log_path: Path, workers: int,
            line: Callable[[dict], str]) -> list[dict]:
    """``run(*job)`` for every job on ``workers`` processes; each row appended to the JSON-lines
    log and printed as it arrives. Returns the rows."""
    rows = []
    with log_path.open("a") as log, ProcessPoolExecutor(workers) as pool:
        for row in pool.map(run, *zip(*jobs, strict=True)):
            rows.append(row)
            log.write(json.dumps(row) + "\n")
            log.flush()
            print(line(row), flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=120)
    parser.add_argument("--first", type=int, default=0, help="index of the first run")
    parser.add_argument("--jobs", type=int, default=1, help="runs in parallel")
    parser.add_argument("--out", type=Path, default=REPO / "out" / "ry-sweep")
    parser.add_argument("--table", action="store_true",
                        help="only print the table of the runs already in --out")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    log_path = args.out / "runs.jsonl"
    if args.table:
        table([json.loads(line) for line in log_path.read_text().splitlines()])
        return
    ks = range(args.first, args.first + args.runs)
    table(run_all(one, [(k, args.out) for k in ks], log_path, args.jobs, _line))


if __name__ == "__main__":
    main()
