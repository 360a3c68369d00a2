"""The lidar–encoder time offset of docs/algorithms.md: simulated offsets recovered from the spin
scan's two passes, and a cube scanned at another speed measured with and without the estimate.

    .venv/bin/python benchmarks/time_offset.py [--offsets 0 2 5 20] [--seeds 2] [--cube-rpm -5]
        [--set simulation.lidar.range_noise=0.002 ...]

Each run simulates recipes/sim-periodicity-both-ways.yaml with the simulated encoder late by the
offset (the station's configuration still says 0), runs the initial calibration, the periodicity
fine-tuning and the time-offset estimate as the station does, then measures the cube from its
two passes (the recipe's 20 rpm and ``--cube-rpm``) together: once with the estimated latency,
once with the configured one. It prints the estimate's error against the simulator's truth, its
σ (and whether the recipe's ``calibration.max_sigma.encoder_latency_ms`` refuses it), and the
face-fit edge error of the cube in each case, with the single pass's for reference. ``--set``
changes the recipe (a dotted key and a YAML value, repeatable) to measure off the simulator's
defaults: more range noise, no background, another line rate or target placement.
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path
from typing import Any

import yaml

from calstation import plugins
from calstation.engine.cube import check_cube, check_cube_passes
from calstation.engine.initial import initial_calibration
from calstation.engine.timeoffset import with_time_offset
from calstation.plugins.cost_strategies import run_strategy
from calstation.recipes import load_recipe
from calstation.recordings.reader import read_recording

REPO = Path(__file__).resolve().parents[1]
RECIPE = REPO / "recipes" / "sim-periodicity-both-ways.yaml"


def _patched(changes: list[str]) -> dict[str, Any]:
    """The recipe's data with ``KEY=VALUE`` changes (dotted keys, YAML values)."""
    data: dict[str, Any] = yaml.safe_load(RECIPE.read_text())
    for change in changes:
        key, sep, text = change.partition("=")
        if not sep:
            raise SystemExit(f"--set {change!r}: expected KEY=VALUE")
        *path, name = key.split(".")
        node = data
        for part in path:
            node = node.setdefault(part, {})
        node[name] = yaml.safe_load(text)
    return data


def one(offset_ms: float, seed: int, cube_rpm: float, out: Path,
        changes: list[str]) -> dict[str, float]:
    """Simulate, calibrate and measure one run; its figures (ms and mm)."""
    from calstation_sim import simulate_run

    data = _patched(changes)
    data["simulation"]["seed"] = seed
    data["simulation"]["encoder"]["latency_s"] = offset_ms * 1e-3
    data["steps"]["cube_scan"]["second_pass_rpm"] = cube_rpm
    path = out / f"recipe-{offset_ms:g}-{seed}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    loaded = load_recipe(path)
    rc = loaded.recipe
    files = simulate_run(loaded, out / f"run-{offset_ms:g}-{seed}", progress=False)
    t0 = time.perf_counter()
    initial = initial_calibration(read_recording(files["static"]), rc.fixtures.static_target,
                                  rc.calibration.initial)
    spin = read_recording(files["spin"])
    result, _ = run_strategy(plugins.strategy(rc.calibration.strategy), spin, initial.H, rc)
    t1 = time.perf_counter()
    result = with_time_offset(result, spin, read_recording(files["spin-pass2"]),
                              rc.fixtures.platter.radius)
    t2 = time.perf_counter()
    assert result.encoder_latency_s is not None and result.sigma_encoder_latency_s is not None
    cubes = [read_recording(files["cube"]), read_recording(files["cube-pass2"])]
    radius = rc.fixtures.platter.radius

    def measured(latency: float | None) -> tuple[float, float, float]:
        """Face-fit edge error, worst face flatness RMS and the paper's OBB edge error (mm) of
        both passes together."""
        check = check_cube_passes(cubes, result.H, rc.fixtures.qa_cube, rc.qa,
                                  encoder_latency_s=latency, platter_radius=radius)
        return check.edge_error * 1e3, check.flatness_rms * 1e3, check.obb_error * 1e3

    (edge_with, flat_with, obb_with), (edge_without, flat_without, obb_without) = measured(
        result.encoder_latency_s), measured(None)

    single = check_cube(cubes[0], result.H, rc.fixtures.qa_cube, rc.qa, platter_radius=radius)
    return {
        "offset_ms": offset_ms,
        "seed": seed,
        "estimate_ms": result.encoder_latency_s * 1e3,
        "error_ms": result.encoder_latency_s * 1e3 - offset_ms,
        "sigma_ms": result.sigma_encoder_latency_s * 1e3,
        "gate_ms": rc.calibration.max_sigma.encoder_latency_ms,
        "edge_with_mm": edge_with,
        "edge_without_mm": edge_without,
        "flat_with_mm": flat_with,
        "flat_without_mm": flat_without,
        "obb_with_mm": obb_with,
        "obb_without_mm": obb_without,
        "edge_single_mm": single.edge_error * 1e3,
        "fine_tune_s": t1 - t0,
        "offset_s": t2 - t1,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--offsets", type=float, nargs="+", default=[0.0, 2.0, 5.0, 20.0],
                        help="simulated offsets (ms)")
    parser.add_argument("--seeds", type=int, default=2, help="seeds per offset (from --seed)")
    parser.add_argument("--seed", type=int, default=100)
    parser.add_argument("--cube-rpm", type=float, default=-5.0,
                        help="speed of the cube's second pass (rpm, negative: the other way)")
    parser.add_argument("--set", dest="changes", action="append", default=[],
                        metavar="KEY=VALUE", help="change the recipe (dotted key, YAML value)")
    args = parser.parse_args()
    changed = f" with {', '.join(args.changes)}" if args.changes else ""
    print(f"recipe {RECIPE.relative_to(REPO)}{changed}, spin 20 / -20 rpm, cube 20 / "
          f"{args.cube_rpm:g} "
          "rpm; the cube's face-fit edge error, worst face flatness (RMS) and the paper's OBB "
          "edge error from both passes, with the estimated latency and without it (the "
          "configured 0)")
    print(f"{'offset':>7} {'seed':>4} {'estimate':>9} {'error':>7} {'σ':>6} {'|e|/σ':>6} "
          f"{'edge with':>10} {'without':>8} {'1 pass':>7} {'flat with':>10} {'without':>8} "
          f"{'fine':>5} {'offset':>6}")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for offset in args.offsets:
            for seed in range(args.seed, args.seed + args.seeds):
                r = one(offset, seed, args.cube_rpm, Path(tmp), args.changes)
                rows.append(r)
                print(f"{r['offset_ms']:6g}ms {seed:4d} {r['estimate_ms']:7.3f}ms "
                      f"{r['error_ms']:+7.3f} {r['sigma_ms']:6.3f} "
                      f"{abs(r['error_ms']) / r['sigma_ms']:6.2f} {r['edge_with_mm']:8.3f}mm "
                      f"{r['edge_without_mm']:6.3f}mm {r['edge_single_mm']:5.3f}mm "
                      f"{r['flat_with_mm']:8.3f}mm {r['flat_without_mm']:6.3f}mm "
                      f"{r['obb_with_mm']:7.3f}mm {r['obb_without_mm']:6.3f}mm "
                      f"{r['fine_tune_s']:4.1f}s {r['offset_s']:5.1f}s"
                      f"{'  refused (σ)' if r['sigma_ms'] > r['gate_ms'] else ''}", flush=True)
    refused = sum(r["sigma_ms"] > r["gate_ms"] for r in rows)
    print(f"refused by the σ gate ({rows[0]['gate_ms']:g} ms): {refused} of {len(rows)}")
    worst = max(abs(r["error_ms"]) for r in rows)
    print(f"worst error {worst:.3f} ms (target 0.2 ms); worst |error|/σ "
          f"{max(abs(r['error_ms']) / r['sigma_ms'] for r in rows):.2f}; worst edge error with "
          f"the estimate {max(r['edge_with_mm'] for r in rows):.3f} mm (target 0.3 mm)")
    if not math.isfinite(worst):
        raise SystemExit(1)


if __name__ == "__main__":
    main()
