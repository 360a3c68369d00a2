"""Time the calibration engine on simulated recordings and print the figures.

    .venv/bin/python benchmarks/calibration.py [--recipe R] [--range 1.25] [--pitch 45]
                                               [--seed 1] [--repeat 3] [--out DIR]

Simulates one run (static, spin and cube scans) unless DIR already holds one, then times, each
``--repeat`` times: reading the recordings, the initial calibration, periodicity fine-tuning from
the initial calibration, shape fine-tuning from it, and the cube check. Prints the median and
the extremes per stage, plus the accuracy against the simulator's truth (DESIGN §8) so a speed-up
that costs accuracy shows. Targets (issue "calibration engine"): initial ≤ 1 s, each fine-tuning
≤ 10 s, cube check ≤ 2 s on a 2-core machine. Figures taken on a busy machine are pessimistic.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]


def _time(fn: Callable[[], Any], repeat: int) -> tuple[list[float], Any]:
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return times, out


def _row(name: str, times: list[float], note: str = "") -> None:
    print(
        f"{name:<26} median {statistics.median(times):7.3f} s   "
        f"min {min(times):7.3f} s   max {max(times):7.3f} s   {note}"
    )


def main() -> None:
    """Run the benchmark and print its figures."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--recipe", default=str(REPO / "recipes/sim-periodicity.yaml"))
    ap.add_argument("--range", type=float, default=1.25, dest="range_m")
    ap.add_argument("--pitch", type=float, default=45.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", type=Path, default=None, help="folder for (or with) the recordings")
    args = ap.parse_args()

    from calstation.cube import check_cube
    from calstation.initial import initial_calibration
    from calstation.metrics import axis_errors, reconstruction_distortion
    from calstation.recipe import load_recipe
    from calstation.recording import read_recording
    from calstation.strategies import PeriodicityStrategy, ShapeStrategy

    loaded = load_recipe(args.recipe)
    rc = loaded.recipe
    out = args.out or Path(tempfile.mkdtemp(prefix="calstation-bench-"))
    if not (out / "truth.json").exists():
        from calstation_sim import simulate_run

        t0 = time.perf_counter()
        simulate_run(
            loaded, out, seed=args.seed, range_m=args.range_m, pitch_deg=args.pitch, progress=False
        )
        print(f"simulated run in {time.perf_counter() - t0:.1f} s → {out}")
    print(
        f"scenario: range {args.range_m} m, pitch {args.pitch}°, seed {args.seed}; "
        f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}"
    )
    t_read, recs = _time(
        lambda: {k: read_recording(out / f"{k}.mcap") for k in ("static", "spin", "cube")}, 1
    )
    _row("read recordings", t_read, f"{recs['spin'].n_points:,} spin-scan points")
    truth = recs["spin"].truth

    t_init, initial = _time(
        lambda: initial_calibration(
            recs["static"], rc.fixtures.static_target, rc.calibration.initial
        ),
        args.repeat,
    )
    _row("initial calibration", t_init)
    results = {"initial": initial}
    for strat, key in ((PeriodicityStrategy(), "spin"), (ShapeStrategy(), "cube")):
        times, res = _time(lambda s=strat, k=key: s.run(recs[k], initial.H, rc), args.repeat)
        _row(f"{strat.name} fine-tuning", times, f"{res.iterations} iterations")
        results[strat.name] = res
    t_cube, check = _time(
        lambda: check_cube(recs["cube"], results["periodicity"].H, rc.fixtures.qa_cube, rc.qa),
        args.repeat,
    )
    _row("cube check", t_cube, f"{check.points:,} cube points, passed={check.passed}")

    if truth is not None:
        print("\naccuracy against the simulator's truth:")
        for name, res in results.items():
            e = axis_errors(res.H, truth)
            d = reconstruction_distortion(recs["cube"], res.H, truth)
            print(
                f"  {name:<12} axis offset {e['axis_offset_m'] * 1e3:6.3f} mm   "
                f"direction {math.degrees(e['axis_angle_rad']):6.3f}°   "
                f"rz {math.degrees(e['rz_error']):+7.4f}°   "
                f"ry {math.degrees(e['ry_error']):+7.3f}°   "
                f"cube distortion {d['rms_m'] * 1e3:.3f} mm RMS"
            )
        print(
            f"  cube check (periodicity H): face-fit edge error {check.edge_error * 1e3:.3f} mm, "
            f"paper OBB e = {check.obb_error * 1e3:.2f} mm"
        )


if __name__ == "__main__":
    main()
