"""Recording throughput: write and read a spin-sized recording (3000 lines × 1000 points).

Prints figures; not a test. The sensor of the paper gives about 1 M points/s, so writing must
keep up with that; reading must reach 10 M points/s (a whole spin scan in a fraction of a
second).

    .venv/bin/python benchmarks/recording_io.py [--lines 3000] [--points 1000]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
import tracemalloc
import warnings
from pathlib import Path

import numpy as np

from calstation.drivers import EncoderSample, LidarInfo, LidarLine
from calstation.engine.frames import Extrinsics
from calstation.engine.reconstruct import reconstruct
from calstation.recordings.files import write_ply
from calstation.recordings.reader import read_recording
from calstation.recordings.writer import RecordingWriter


def main() -> None:
    """Run the benchmark and print the figures."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--lines", type=int, default=3000)
    ap.add_argument("--points", type=int, default=1000)
    args = ap.parse_args()
    n_lines, n = args.lines, args.points
    info = LidarInfo("bench", "line", "0", np.deg2rad(72), n, 1000.0, 0.2, 10.0)
    rng = np.random.default_rng(0)
    az = np.linspace(-0.63, 0.63, n)
    t0 = 1_767_225_600_000_000_000
    lines = [
        LidarLine(
            timestamp_ns=t0 + i * 1_000_000,
            azimuth_rad=az,
            range_m=1.2 + 0.05 * np.sin(az * 7 + i * 1e-3) + 0.001 * rng.standard_normal(n),
            valid=rng.random(n) > 0.002,
            point_period_ns=1000.0,
        )
        for i in range(n_lines)
    ]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bench.mcap"
        start = time.perf_counter()
        with RecordingWriter(
            path, kind="spin", lidar_info=info, counts_per_revolution=4096, encoder_direction=1
        ) as w:
            for i, line in enumerate(lines):
                w.write_line(line)
                w.write_encoder([EncoderSample(t0 + i * 1_000_000, i * 4)])
            w.write_encoder([EncoderSample(t0 + n_lines * 1_000_000, n_lines * 4)])
        t_write = time.perf_counter() - start
        size = path.stat().st_size
        m = n_lines * n
        print(f"points:        {m:,} ({n_lines} lines × {n})")
        print(f"write:         {t_write:.2f} s = {m / t_write / 1e6:.1f} M points/s "
              f"(sensor: 1 M points/s)")
        print(f"file size:     {size / 1e6:.1f} MB ({size / m:.1f} bytes/point)")

        times, cpu = [], []
        for _ in range(5):
            start, start_cpu = time.perf_counter(), time.process_time()
            with warnings.catch_warnings():
                warnings.simplefilter("error")
                rec = read_recording(path)
            times.append(time.perf_counter() - start)
            cpu.append(time.process_time() - start_cpu)
        t_read = min(times)
        tracemalloc.start()
        read_recording(path)
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        rate = m / t_read / 1e6
        print(f"read:          {t_read:.2f} s (best of 5; worst {max(times):.2f} s) = "
              f"{rate:.1f} M points/s (target ≥ 10: {'met' if rate >= 10 else 'NOT met'}), "
              f"peak memory {peak / 1e6:.0f} MB")
        # on a shared machine the wall time includes waiting for a core: say how busy it was
        print(f"read, CPU:     {min(cpu):.2f} s of this process = {m / min(cpu) / 1e6:.1f} M "
              f"points/s; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")

        start = time.perf_counter()
        points = reconstruct(rec, Extrinsics(ty=1.2, rz=-0.785))
        t_rec = time.perf_counter() - start
        start = time.perf_counter()
        write_ply(Path(tmp) / "bench.ply", points)
        t_ply = time.perf_counter() - start
        print(f"reconstruct:   {t_rec:.2f} s ({len(points):,} points)")
        print(f"write PLY:     {t_ply:.2f} s")


if __name__ == "__main__":
    main()
