"""The sensor sweep of docs/algorithms.md: whole simulated station runs of a lidar with systematic
range errors (DESIGN §9), each decided as the station decides it, against the physical truth.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/sensor_sweep.py run [--runs 60] [--jobs 2]
    .venv/bin/python benchmarks/sensor_sweep.py table --out DIR

Each run is a ``calstation run`` of recipes/sim-periodicity.yaml (``--recipe``) with one
combination of the sweep's conditions — range offset (−10, −3, 0, +3, +10 mm), scale error (−0.1
%, 0, +0.1 %; −K, 0, +K with ``--scale-level K``), incidence bias (none, 0.5 mm at 60°), range
noise (0.5, 1 mm), line rate (180, 1000 lines/s) and placement (the recipe's; the spin target
and the cube elsewhere and turned) — the combinations taken in a fixed shuffled order, so that
any first N runs cover every level of every factor about evenly. The recipe's
``calibration.range_model`` (``--range-model`` replaces it) is what is estimated; the QA cube is
a certified one (``--edge-tolerance``, 5 µm). The recipe's other sensor errors stay: with
``--recipe recipes/sim-realistic.yaml`` each run also has its reflectivities, mixed pixels,
warm-up drift, encoder, axis and platter errors, and the range offset is judged against the one
the lidar has on the QA cube (its offset, its drift at the time and the cube's reflectivity
bias).

With ``--certificate SIGMA`` each lidar also has a range offset certificate
(``calibration.range_offset_certificate``) of that σ, its value the lidar's true offset plus an
error drawn from it, as a range bench would state it.

Printed, over the runs and per condition: how many were accepted; of the accepted, whether tx,
ty, tz, ry, rz are within 3σ of the physical H and the range offset within 3σ of its truth (the
lidar's offset plus what its scale error adds at the platter's range when the scale is not
estimated: the offset such a lidar has there); the axis offset and direction (median, max); the
cube reconstructed with the result (its face-fit edge error and squareness, median); and whether
the predicted error covered the true reconstruction error over the work volume (the range
models of the estimate and of the truth in both).
"""

from __future__ import annotations

import argparse
import copy
import itertools
import json
import math
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from calstation.recipes import LoadedRecipe, parse_recipe
from calstation.recipes.simulation import Reflectivity

REPO = Path(__file__).resolve().parents[1]
OFFSETS = (-0.010, -0.003, 0.0, 0.003, 0.010)
SCALES = (-0.001, 0.0, 0.001)
INCIDENCE = (0.0, 0.0005)
NOISES = (0.0005, 0.001)
RATES = (180.0, 1000.0)
PLACEMENTS = (
    {},
    {"spin_target": {"offset": [-0.05, 0.04]}, "qa_cube": {"offset": [-0.07, -0.06],
                                                           "yaw_deg": 35}},
)
CONDITIONS = list(itertools.product(OFFSETS, SCALES, INCIDENCE, NOISES, RATES,
                                    range(len(PLACEMENTS))))
"""(offset m, scale, incidence bias m at 60°, range noise m, line rate, placement)"""
ORDER = np.random.default_rng(2026).permutation(len(CONDITIONS)).tolist()
PARAMS = ("tx", "ty", "tz", "ry", "rz")


def condition(k: int, scale_level: float = SCALES[-1]) -> dict[str, Any]:
    """The conditions of run ``k``; its scale error ``scale_level`` times its level (−1, 0,
    +1), so that a recipe's stated scale σ can bound the lidars it is swept over."""
    offset, scale, incidence, noise, rate, place = CONDITIONS[ORDER[k % len(CONDITIONS)]]
    return {"offset": offset, "scale": scale / SCALES[-1] * scale_level,
            "incidence": incidence, "noise": noise, "line_rate": rate, "placement": place}


def sensor_recipe(k: int, recipe: Path, range_model: str | None,
                  edge_tolerance: float, certificate: float | None = None,
                  scale_level: float = SCALES[-1]) -> LoadedRecipe:
    """``recipe`` with run ``k``'s lidar, placement and seed; with ``certificate`` (m), the
    lidar's range offset certificate of that σ, its value the lidar's offset plus an error
    drawn from it (seeded by ``k``), as a range bench would state it."""
    c = condition(k, scale_level)
    data = copy.deepcopy(yaml.safe_load(recipe.read_text()))
    sim = data["simulation"]
    sim["seed"] = 500 + k
    sim["lidar"].update(range_noise=c["noise"], line_rate_hz=c["line_rate"])
    # the recipe's other errors (reflectivity, mixed pixels, warm-up, encoder, axis, platter:
    # recipes/sim-realistic.yaml) stay; the run's range terms replace its own
    sim["sensor"] = {**(sim.get("sensor") or {}),
                     "range": {"offset": c["offset"], "scale": c["scale"],
                               "incidence_bias": c["incidence"]}}
    for fixture, values in PLACEMENTS[c["placement"]].items():
        data["fixtures"][fixture].update(values)
    # the simulated cube and platter read alike unless the recipe gives them reflectivities
    # of their own (offset+scale needs them alike; sim-realistic.yaml's do not)
    reflectivity = Reflectivity.model_validate(sim["sensor"].get("reflectivity") or {})
    same = reflectivity.range_bias("platter") == reflectivity.range_bias("qa_cube")
    data["fixtures"]["qa_cube"].update(edge_tolerance=edge_tolerance,
                                       same_finish_as_platter=same)
    if range_model is not None:
        data.setdefault("calibration", {})["range_model"] = range_model
    if certificate is not None:
        stated = c["offset"] + float(np.random.default_rng(9000 + k).normal(0.0, certificate))
        data.setdefault("calibration", {})["range_offset_certificate"] = {
            "offset": stated, "sigma": certificate}
    text = yaml.safe_dump(data)
    return LoadedRecipe(parse_recipe(text, f"sensor sweep run {k}"), None, text)


def station_run(k: int, out: Path, recipe: Path, range_model: str | None,
                edge_tolerance: float, certificate: float | None = None,
                scale_level: float = SCALES[-1]) -> dict[str, Any]:
    """Run ``k`` as a whole simulated station run; its row (SI units)."""
    from ry_sweep import unattended_run  # as the capability sweep runs its station runs

    row = unattended_run(sensor_recipe(k, recipe, range_model, edge_tolerance, certificate,
                                       scale_level), out / f"run{k}", _row)
    row.update(k=k, **condition(k, scale_level))
    return row


def _row(db: Any, run_id: int, status: str, loaded: LoadedRecipe) -> dict[str, Any]:
    """What the station decided, its final estimate against the truth."""
    from calstation.engine.accuracy import true_distortion
    from calstation.engine.cube import check_cube
    from calstation.engine.metrics import axis_errors
    from calstation.engine.rangemodel import RangeModel
    from calstation.recordings.reader import read_recording
    from calstation.storage.db import Artifact, Calibration, Step

    recipe = loaded.recipe
    with db.session() as s:
        cals = s.query(Calibration).filter_by(run_id=run_id).order_by(Calibration.id).all()
        final = next((c for c in cals if c.accepted), None) or next(
            (c for c in reversed(cals) if c.stage == "fine"), None)
        result = None if final is None else final.result()
        paths = {a.kind: a.path for a in s.query(Artifact).filter_by(run_id=run_id)}
        failed = [st.error for st in s.query(Step).filter_by(run_id=run_id)
                  if st.status == "failed" and st.error]
    row: dict[str, Any] = {"status": status, "accepted": status == "passed",
                           "failure": failed[:1]}
    if result is None or "cube" not in paths:
        return row
    cube = read_recording(paths["cube"])
    truth, meta = cube.truth, cube.metadata["truth"]
    assert truth is not None
    on_cube = _on_cube(meta["sensor"])
    true_range = RangeModel(meta["range_offset"] + on_cube, meta["range_scale"])
    accuracy = recipe.calibration.accuracy
    check = check_cube(cube, result.H, recipe.fixtures.qa_cube, recipe.qa,
                       platter_radius=recipe.fixtures.platter.radius,
                       range_model=result.range_model)
    row.update(
        err=axis_errors(result.H, truth),
        sigma={p: result.sigma.get(p) for p in PARAMS},
        ranges=result.range_fields(),
        true_range={"offset": meta["range_offset"], "scale": true_range.scale,
                    "incidence_bias": meta["sensor"]["range"]["incidence_bias"],
                    "on_cube": on_cube},
        predicted_error_m=final.predicted_error_m if final is not None else None,
        true_distortion_m=true_distortion(
            result.H, truth, radius=accuracy.work_radius(recipe.fixtures.platter),
            height=accuracy.height, estimate_range=result.range_model,
            truth_range=true_range)["max_m"],
        cube={"edge_error_m": check.edge_error, "squareness_deg": check.perpendicularity_deg},
        platter_range_m=float(np.linalg.norm(truth.t)),
    )
    return row


def _on_cube(sensor: dict[str, Any]) -> float:
    """What the lidar adds to its constant offset on the QA cube while the cube turns: its
    warm-up drift then and the cube's reflectivity bias (docs/simulator.md). The range offset
    the station measures is the one its fixtures show; 0 on a lidar without either."""
    reflectivity = Reflectivity.model_validate(sensor.get("reflectivity") or {})
    return float(sensor.get("warmup_drift_now_m") or 0.0) + reflectivity.range_bias("qa_cube")


def _offset_truth(r: dict[str, Any]) -> float:
    """The range offset the estimate is judged against: the lidar's on the QA cube (its offset,
    warm-up drift and the cube's reflectivity bias). A scale error the station does not
    estimate is not in it: the fixtures read a scaled world, which moves H's translation by
    k·t and leaves the offset (:func:`calstation.engine.rangemodel.with_unmeasured_scale`; over
    the realistic station's 24 runs, the offset's error against k·ρ had a slope of 0.05)."""
    t = r["true_range"]
    return float(t["offset"] + t.get("on_cube", 0.0))


def _covered(r: dict[str, Any]) -> bool:
    """Every parameter and the range offset within 3σ of the truth."""
    for p in PARAMS:
        sigma = r["sigma"].get(p)
        if sigma is None or not math.isfinite(sigma) or abs(r["err"][f"{p}_error"]) > 3 * sigma:
            return False
    sigma = r["ranges"].get("sigma_range_offset")
    value = r["ranges"].get("range_offset")
    if value is None:
        return True
    return sigma is not None and abs(value - _offset_truth(r)) <= 3 * sigma


def table(rows: list[dict[str, Any]]) -> None:
    """The sweep's figures, over all runs and per factor."""
    def summary(sel: list[dict[str, Any]], label: str) -> None:
        acc = [r for r in sel if r["accepted"] and "err" in r]
        if not sel:
            return
        off = [r["err"]["axis_offset_m"] * 1e3 for r in acc]
        ang = [math.degrees(r["err"]["axis_angle_rad"]) for r in acc]
        cov = sum(_covered(r) for r in acc)
        edge = [abs(r["cube"]["edge_error_m"]) * 1e3 for r in acc]
        sq = [r["cube"]["squareness_deg"] for r in acc]
        pred = [r for r in acc if r.get("predicted_error_m") is not None]
        covered = sum(r["true_distortion_m"] <= r["predicted_error_m"] for r in pred)
        print(f"{label:28} {len(acc):3}/{len(sel):3} accepted; within 3σ {cov}/{len(acc)}; "
              f"axis offset median {np.median(off) if off else math.nan:.3f} max "
              f"{max(off) if off else math.nan:.3f} mm; direction median "
              f"{np.median(ang) if ang else math.nan:.4f} max {max(ang) if ang else math.nan:.4f}°;"
              f" cube edge {np.median(edge) if edge else math.nan:.3f} mm, squareness "
              f"{np.median(sq) if sq else math.nan:.3f}° (median); predicted ≥ true "
              f"{covered}/{len(pred)}")

    summary(rows, "all")
    scales = sorted({float(r["scale"]) for r in rows})
    for key, levels in (("offset", OFFSETS), ("scale", scales), ("incidence", INCIDENCE),
                        ("noise", NOISES), ("line_rate", RATES),
                        ("placement", range(len(PLACEMENTS)))):
        for v in levels:
            summary([r for r in rows if math.isclose(r[key], v)], f"  {key} {v:g}")
    for r in rows:
        if not r["accepted"]:
            print(f"    refused run {r['k']}: {str(r['failure'][:1])[:300]}")


def _line(r: dict[str, Any]) -> str:
    head = (f"run {r['k']}: offset {r['offset'] * 1e3:+.0f} mm, scale {r['scale'] * 1e6:+.0f} ppm, "
            f"incidence {r['incidence'] * 1e3:.1f} mm, {r['noise'] * 1e3:.1f} mm, "
            f"{r['line_rate']:.0f} lines/s, placement {r['placement']}: "
            f"{'accepted' if r['accepted'] else 'refused'}")
    if "err" in r:
        e = r["err"]
        head += (f"; axis {e['axis_offset_m'] * 1e3:.3f} mm, "
                 f"{math.degrees(e['axis_angle_rad']):.4f}°, b "
                 f"{(r['ranges']['range_offset'] or 0) * 1e3:+.3f} ± "
                 f"{(r['ranges']['sigma_range_offset'] or math.nan) * 1e3:.3f} mm "
                 f"(true {_offset_truth(r) * 1e3:+.3f}), within 3σ {_covered(r)}")
    return head


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("mode", choices=("run", "table"))
    ap.add_argument("--runs", type=int, default=60)
    ap.add_argument("--first", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--recipe", type=Path, default=REPO / "recipes/sim-periodicity.yaml")
    ap.add_argument("--range-model", default=None, choices=("none", "offset", "offset+scale"))
    ap.add_argument("--edge-tolerance", type=float, default=5e-6)
    ap.add_argument("--certificate", type=float, default=None, metavar="SIGMA",
                    help="give each lidar a range offset certificate of this σ (m), its value "
                    "drawn about the true offset")
    ap.add_argument("--scale-level", type=float, default=SCALES[-1], metavar="K",
                    help="the scale errors swept: −K, 0 and +K (default 0.001)")
    ap.add_argument("--out", type=Path, default=REPO / "out" / "sensor-sweep")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    log = args.out / "runs.jsonl"
    if args.mode == "run":
        import sys

        sys.path.insert(0, str(Path(__file__).resolve().parent))
        jobs = [(k, args.out, args.recipe, args.range_model, args.edge_tolerance,
                 args.certificate, args.scale_level)
                for k in range(args.first, args.first + args.runs)]
        with log.open("a") as f, ProcessPoolExecutor(args.jobs) as pool:
            for row in pool.map(station_run, *zip(*jobs, strict=True)):
                f.write(json.dumps(row, default=float) + "\n")
                f.flush()
                print(_line(row), flush=True)
    rows = [json.loads(line) for line in log.read_text().splitlines()]
    table(rows)


if __name__ == "__main__":
    main()
