"""Simulate one platter revolution at 1 M points/s and print wall time and peak memory.

    .venv/bin/python benchmarks/simulate_revolution.py [--recipe R] [--rpm 20] [--no-write]

Times the simulated station alone (ray casting, noise, mixed pixels, driver loop) and the whole
spin scan written to an MCAP recording, as ``calstation simulate`` does. Peak memory is the
process's peak resident set size (it includes Python, NumPy and Open3D themselves, so the
baseline after imports is printed too). Figures taken on a busy machine are pessimistic.
"""

from __future__ import annotations

import argparse
import resource
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _peak_mib() -> float:
    kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kib / 1024.0 if sys.platform != "darwin" else kib / 2**20


def main() -> None:
    """Run the benchmark and print its figures."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--recipe", default=str(REPO / "recipes/sim-periodicity.yaml"))
    ap.add_argument("--rpm", type=float, default=20.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--no-write", action="store_true", help="skip the recording pass")
    args = ap.parse_args()

    from calstation_sim import SimEncoder, SimLidar, SimTurntable, SimulatedStation

    from calstation.recipes import SimulationConfig, load_recipe
    from calstation.recordings.writer import RecordingWriter
    from calstation.station.acquisition import acquire_spin

    recipe = load_recipe(args.recipe)
    base = _peak_mib()
    sim = recipe.recipe.simulation or SimulationConfig()
    lm = sim.lidar
    rate = lm.points_per_line * lm.line_rate_hz
    print(
        f"lidar: {lm.points_per_line} points/line × {lm.line_rate_hz:g} lines/s "
        f"= {rate:,.0f} points/s"
    )
    print(f"turntable: {args.rpm:g} rpm → one revolution = {60 / args.rpm:g} s of scan")
    print(f"peak RSS after imports: {base:.0f} MiB")

    # 1. the simulator alone: one revolution of lines through the driver
    station = SimulatedStation(recipe, seed=args.seed)
    station.place("spin_target")
    lidar = SimLidar(station)
    station.set_speed(args.rpm, station.clock.now_ns())
    station.clock.sleep(args.rpm / sim.turntable.acceleration_rpm_s)  # the ramp
    n_lines = round(60.0 / args.rpm * lm.line_rate_hz)
    t0 = time.perf_counter()
    lidar.start()
    points = valid = 0
    for i, line in enumerate(lidar.lines()):
        points += len(line)
        valid += int(line.valid.sum())
        if i + 1 >= n_lines:
            break
    lidar.stop()
    dt = time.perf_counter() - t0
    print(
        f"simulate one revolution: {n_lines} lines, {points:,} points ({valid / points:.1%} valid) "
        f"in {dt:.2f} s wall = {points / dt / 1e6:.2f} M points/s; peak RSS {_peak_mib():.0f} MiB"
    )

    if args.no_write:
        return
    # 2. the whole spin scan as `calstation simulate` records it
    station = SimulatedStation(recipe, seed=args.seed)
    station.place("spin_target")
    lidar, turntable, encoder = SimLidar(station), SimTurntable(station), SimEncoder(station)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "spin.mcap"
        t0 = time.perf_counter()
        with RecordingWriter(
            path,
            kind="spin",
            lidar_info=lidar.info(),
            counts_per_revolution=encoder.counts_per_revolution,
            encoder_direction=recipe.recipe.station.encoder.direction,
            recipe=recipe,
            metadata={"truth": station.truth_dict()},
            clock=station.clock,
        ) as writer:
            acquire_spin(
                lidar,
                turntable,
                encoder,
                writer,
                rpm=args.rpm,
                revolutions=1.0,
                settle_s=0.0,
                clock=station.clock,
            )
        dt = time.perf_counter() - t0
        size = path.stat().st_size
    print(
        f"spin scan of one revolution recorded to MCAP: {dt:.2f} s wall, "
        f"{size / 2**20:.1f} MiB file; peak RSS {_peak_mib():.0f} MiB"
    )


if __name__ == "__main__":
    main()
