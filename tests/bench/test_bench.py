"""The paper bench: scenarios, perturbed starts, and a quick end-to-end run on the simulator."""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from calstation.bench import BenchError
from calstation.bench.scenarios import (
    PERTURBATION_SETS,
    paper_scenarios,
    sample_starts,
    select_scenarios,
)
from calstation.bench.worker import apply_overrides
from calstation.engine.frames import Extrinsics
from calstation.recipes import load_recipe

ROOT = Path(__file__).resolve().parents[2]


def _calstation(*args: str, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    """``calstation ARGS`` in a process of its own, as an operator runs it."""
    exe = Path(sys.executable).parent / "calstation"
    return subprocess.run([str(exe), *args], capture_output=True, text=True, timeout=timeout)


RECIPE = ROOT / "recipes" / "sim-periodicity.yaml"


def test_nine_paper_scenarios() -> None:
    scen = paper_scenarios()
    assert [s.name for s in scen] == [f"D{i}" for i in range(1, 10)]
    grid = {(s.range_m, s.pitch_deg) for s in scen}
    assert grid == {(r, p) for r in (1.0, 1.25, 1.5) for p in (30.0, 45.0, 60.0)}
    # the paper's table: D1..D3 at 30°, ranges increasing along the row
    assert (scen[0].range_m, scen[0].pitch_deg) == (1.0, 30.0)
    assert (scen[5].range_m, scen[5].pitch_deg) == (1.5, 45.0)
    assert len({s.seed for s in scen}) == 9
    assert [s.name for s in select_scenarios(["d6", "D1"])] == ["D6", "D1"]
    with pytest.raises(BenchError, match="D10"):
        select_scenarios(["D10"])


@pytest.mark.parametrize("set_name", ["A", "B"])
def test_perturbed_starts_follow_the_paper(set_name: str) -> None:
    h0 = Extrinsics(0.01, 1.2, -0.003, 0.0, 0.002, -0.78)
    pset = PERTURBATION_SETS[set_name]
    starts = sample_starts(h0, pset, 50, scenario_index=4)
    d = np.array([s.as_vector() - h0.as_vector() for s in starts])
    t, r = pset.translation_m, math.radians(pset.rotation_deg)
    assert np.all(d[:, 1] == 0.0), "ty is fixed"
    assert np.all(np.array([s.rx for s in starts]) == 0.0), "rx stays at its gauge"
    assert np.all(np.abs(d[:, [0, 2]]) <= t) and np.all(np.abs(d[:, [4, 5]]) <= r)
    # uniform over the box: 50 samples reach well into every corner direction
    assert np.all(np.max(np.abs(d[:, [0, 2]]), axis=0) > 0.8 * t)
    assert np.all(np.max(np.abs(d[:, [4, 5]]), axis=0) > 0.8 * r)
    assert np.all(d[:, [0, 2, 4, 5]].mean(axis=0) < np.array([t, t, r, r]) / 3)
    # seeded and prefix-stable: a shorter run uses the first starts of a longer one
    again = sample_starts(h0, pset, 10, scenario_index=4)
    assert again == starts[:10]
    assert sample_starts(h0, pset, 10, scenario_index=5) != starts[:10]


def test_sets_a_and_b_draw_different_starts() -> None:
    h0 = Extrinsics(0.0, 1.0, 0.0, 0.0, 0.0, -0.7)
    a = sample_starts(h0, PERTURBATION_SETS["A"], 5, 0)
    b = sample_starts(h0, PERTURBATION_SETS["B"], 5, 0)
    assert all(x != y for x, y in zip(a, b, strict=True))


def test_recipe_overrides_are_validated() -> None:
    recipe = load_recipe(RECIPE).recipe
    off = apply_overrides(recipe, {"calibration": {"periodicity": {"coarse_to_fine": False}}})
    assert off.calibration.periodicity.coarse_to_fine is False
    assert off.calibration.shape == recipe.calibration.shape
    with pytest.raises(BenchError, match="coarse_to_fin"):
        apply_overrides(recipe, {"calibration": {"periodicity": {"coarse_to_fin": False}}})


def _axis_errors(H: dict[str, float], truth: dict[str, float]) -> tuple[float, float]:
    """Axis offset (m) and direction error (rad), computed here from the definitions in
    DESIGN §8, independently of calstation.engine.metrics."""
    from scipy.spatial.transform import Rotation

    def axis(h: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
        R = Rotation.from_euler("xyz", [h["rx"], h["ry"], h["rz"]]).as_matrix()
        return np.array([h["tx"], h["ty"], h["tz"]]), R[:, 0]

    p_est, d_est = axis(H)
    p_true, d_true = axis(truth)
    angle = math.acos(min(1.0, abs(float(d_est @ d_true))))
    # the estimated axis meets the plane through the true platter centre normal to the true axis
    s = float((p_true - p_est) @ d_true) / float(d_est @ d_true)
    offset = float(np.linalg.norm(p_est + s * d_est - p_true))
    return offset, angle


def test_quick_bench_completes_and_periodicity_meets_thresholds(tmp_path: Path) -> None:
    out = tmp_path / "bench"
    proc = _calstation("bench", "paper", "--quick", "--workers", "2", "--out", str(out),
                       "--recipe", str(RECIPE))
    assert proc.returncode == 0, proc.stderr[-3000:]

    records = [json.loads(line) for line in (out / "records.jsonl").read_text().splitlines()]
    kinds = {r["kind"] for r in records}
    assert {"simulate", "initial", "finetune"} <= kinds
    truth = json.loads((out / "scenarios" / "D5" / "truth.json").read_text())

    periodicity = [r for r in records if r["kind"] == "finetune" and r["method"] == "periodicity"
                   and r["variant"] == "default"]
    # the quick subset: from the initial calibration and from one set-A start
    assert {r["set"] for r in periodicity} == {"init", "A"}
    for r in periodicity:
        assert r["status"] == "ok", r.get("error_message")
        offset, angle = _axis_errors(r["H"], truth)
        assert offset <= 0.5e-3, (r["id"], offset)
        assert math.degrees(angle) <= 0.1, (r["id"], math.degrees(angle))
        assert abs(math.degrees(r["H"]["rz"] - truth["rz"])) <= 0.05, r["id"]
        assert r["converged"] is True
    # the set-A/B starts really were perturbed, so convergence is not a no-op
    starts = [r["start"] for r in periodicity if r["set"] != "init"]
    assert all(abs(s["tx"] - truth["tx"]) > 1e-3 or abs(s["tz"] - truth["tz"]) > 1e-3
               for s in starts)

    shape = [r for r in records if r["kind"] == "finetune" and r["method"] == "shape"]
    assert [r["set"] for r in shape] == ["init"] and shape[0]["status"] == "ok"
    assert shape[0]["cube"]["obb_error_m"] > 0.0  # the paper's OBB error is biased upward
    ablation = [r for r in records if r["variant"] == "no coarse-to-fine"]
    assert len(ablation) == 1 and ablation[0]["status"] == "ok"
    landscape = [r for r in records if r["kind"] == "landscape"]
    assert {(r["landscape"]["method"], r["landscape"]["pair_name"]) for r in landscape} == {
        (m, p) for m in ("shape", "periodicity") for p in ("translation", "rotation")
    }
    grids: dict[tuple[str, str], dict[int, list[float]]] = {}
    for r in landscape:
        ls = r["landscape"]
        assert all(c is not None and c > 0 for c in ls["costs"])
        grids.setdefault((ls["method"], ls["pair_name"]), {})[ls["row"]] = ls["costs"]
    # both costs are sharp in translation: the converged value (grid centre) is the minimum of
    # a ±20 mm grid in tx × tz
    for method in ("shape", "periodicity"):
        g = np.array([grids[(method, "translation")][i] for i in range(3)])
        assert g[1, 1] == g.min(), (method, g)

    md = (out / "results.md").read_text()
    for heading in ("paper Table II", "paper Table III", "Against the paper, in short",
                    "Against the true H", "Spread over perturbed starts", "Cost landscapes",
                    "Ablation", "Time per stage", "Git commit"):
        assert heading in md
    assert re.search(r"load average \d+\.\d at the start and \d+\.\d at the end", md)
    for png in ("param_spread.png", "cube_error.png", "ablation.png",
                "landscape_translation.png", "landscape_rotation.png"):
        data = (out / "results" / png).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000


def test_variant_reports_are_summarised_with_a_link(tmp_path) -> None:
    from calstation.bench.report import variants_section

    assert variants_section(tmp_path) == ""
    report = tmp_path / "bench-variants" / "noise-2mm" / "results.md"
    report.parent.mkdir(parents=True)
    report.write_text("# Results\n\n## Against the true H\n\nSome text.\n\n| a | b |\n|---|---|\n"
                      "| periodicity | 0.05 |\n\n## Spread\n\n| not | this |\n")
    text = variants_section(tmp_path)
    assert "## Harder stations" in text
    assert "[its report](bench-variants/noise-2mm/results.md)" in text
    assert "| periodicity | 0.05 |" in text and "| not | this |" not in text


def test_basin_starts_move_the_named_parameters_by_the_levels_distance() -> None:
    from calstation.bench.basin import PARAMS, ROTATIONS_DEG, TRANSLATIONS_M, basin_starts

    truth = Extrinsics(0.01, 1.25, 0.002, 0.0, 0.003, -0.78)
    starts = basin_starts(truth, 3)
    assert starts == basin_starts(truth, 3)  # repeatable
    assert len(starts) == (len(PARAMS) + 1) * len(TRANSLATIONS_M) * 3
    for s in starts:
        x = dict(zip(("tx", "ty", "tz", "rx", "ry", "rz"), s["start"], strict=True))
        assert x["ty"] == truth.ty and x["rx"] == 0.0
        moved = PARAMS if s["group"] == "joint" else (s["group"],)
        for p in PARAMS:
            d = abs(x[p] - getattr(truth, p))
            full = (TRANSLATIONS_M[s["level"]] if p in ("tx", "tz")
                    else math.radians(ROTATIONS_DEG[s["level"]]))
            if p in moved:
                assert 0.8 * full - 1e-12 <= d <= full + 1e-12
            else:
                assert d == 0.0


def test_basin_section_counts_refused_starts_as_not_converged(tmp_path: Path) -> None:
    from calstation.bench.basin import basin_figure, basin_markdown, silently_wrong

    H = {"tx": 0.01, "ty": 1.25, "tz": 0.0, "rx": 0.0, "ry": 0.0, "rz": -0.78}
    small = {"tx": 1e-5, "ty": 1e-5, "tz": 1e-5, "rx": math.nan, "ry": 1e-4, "rz": 1e-4}
    large = {**small, "ry": 0.01}
    records = [
        {"id": f"r{i}", "method": "periodicity", "group": "tx", "level": 0, "status": status,
         "converged": conv, "H": H, "sigma": sigma}
        for i, (status, conv, sigma) in enumerate([
            ("ok", True, small), ("ok", False, small), ("failed", False, {}), ("ok", True, small),
            ("ok", False, large)])
    ]
    meta = {"methods": ["periodicity"], "command": "calstation bench basin", "git_commit": "x",
            "wall_s": 60.0, "workers": 2, "scenario": "D5", "starts": 4}
    md = basin_markdown(records, meta)
    assert "| tx | 5 mm: 40% |" in md and "1 of them refused" in md
    # of the two estimates outside the thresholds, only r1's σ would pass the default limits
    assert silently_wrong(records) == [records[1]]
    assert "Of the 2 estimates returned outside the thresholds, 1 has" in md
    basin_figure(records, ["periodicity"], tmp_path / "basin.png")
    assert (tmp_path / "basin.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.slow
def test_basin_run_on_the_simulator_and_its_section_in_results(tmp_path: Path) -> None:
    """One start per parameter and level, periodicity only (~40 s on two cores): close starts
    converge, a start 500 mm off in tx is refused, and the section lands in the report."""
    out = tmp_path / "basin"
    proc = _calstation("bench", "basin", "--starts", "1", "--methods", "periodicity", "--out",
                       str(out), "--recipe", str(RECIPE))
    assert proc.returncode == 0, proc.stderr[-3000:]
    records = [json.loads(line) for line in (out / "records.jsonl").read_text().splitlines()]
    by = {(r["group"], r["level"]): r for r in records}
    assert all(by[(g, 0)]["converged"] for g in ("tx", "tz", "ry", "rz", "joint"))
    assert by[("tx", 6)]["status"] == "failed" and not by[("tx", 6)]["converged"]
    md = (out / "basin.md").read_text()
    assert "## Basin of convergence" in md and "| joint |" in md
    assert (out / "results" / "basin.png").is_file()
    bad = _calstation("bench", "basin", "--methods", "nope", "--out", str(out), timeout=120)
    assert bad.returncode != 0 and "unknown strategy nope" in bad.stdout + bad.stderr


def test_speed_recipe_changes_only_the_scans_speed(tmp_path: Path) -> None:
    from calstation.bench.speed import speed_recipe

    fast = load_recipe(RECIPE).recipe
    path, ppl = speed_recipe(RECIPE, 10.0, tmp_path / "r10.yaml")
    ten = load_recipe(path).recipe
    assert ten.steps.spin_scan.rpm == 10.0 and ten.steps.cube_scan.rpm == 10.0
    assert ppl == 1000 and ten.simulation == fast.simulation
    assert ten.calibration == fast.calibration
    assert ten.steps.spin_scan.revolutions == fast.steps.spin_scan.revolutions
    # 1 rpm at 1000 lines/s would make ~63 M returns: fewer points per line, the same line rate
    path, ppl = speed_recipe(RECIPE, 1.0, tmp_path / "r1.yaml")
    one = load_recipe(path).recipe  # valid: within the simulator's 25 M returns per scan
    assert one.simulation is not None and fast.simulation is not None
    assert one.simulation.lidar.points_per_line == ppl < 400
    assert one.simulation.lidar.line_rate_hz == fast.simulation.lidar.line_rate_hz


@pytest.mark.slow
def test_speed_run_and_its_section(tmp_path: Path) -> None:
    out = tmp_path / "speed"
    proc = _calstation("bench", "speed", "--rpm", "10", "--methods", "periodicity", "--out",
                       str(out), "--recipe", str(RECIPE))
    assert proc.returncode == 0, proc.stderr[-3000:]
    (rec,) = json.loads((out / "records.json").read_text())
    assert rec["rpm"] == 10 and rec["status"] == "ok" and rec["axis_offset_m"] < 0.5e-3
    assert rec["lines"] > 6000  # 1.05 turns at 1000 lines/s
    md = (out / "speed.md").read_text()
    assert "| 10 rpm | 6,000 | 1000 | periodicity |" in md
    assert (out / "results" / "speed.png").is_file()
    bad = _calstation("bench", "speed", "--rpm", "0", timeout=120)
    assert bad.returncode != 0 and "within 0.1–120 rpm" in bad.stdout + bad.stderr


@pytest.mark.slow
def test_targetless_run_and_its_section(tmp_path: Path) -> None:
    """One station of D5 and one of E2: both fine-tunings converge from both starts, and the
    section counts them."""
    out = tmp_path / "targetless"
    proc = _calstation("bench", "targetless", "--seeds", "1", "--scenarios", "D5,E2",
                       "--no-geometry", "--out",
                       str(out), "--recipe", str(RECIPE))
    assert proc.returncode == 0, proc.stderr[-3000:]
    records = json.loads((out / "records.json").read_text())
    assert [r["scenario"] for r in records] == ["D5", "E2"]
    for r in records:
        assert r["targetless"]["converged"] and r["l_target"]["converged"], r
        # the start came from the platter's chord: rz within a tenth of a degree
        assert abs(r["targetless"]["start"]["error"]["rz"]) < math.radians(0.1)
    md = (out / "targetless.md").read_text()
    assert "**Converged: 2/2 from the platter (100.0 %), 2/2 from the L-target.**" in md
    assert (out / "results" / "targetless.png").is_file()
    bad = _calstation("bench", "targetless", "--scenarios", "D10", "--out", str(out),
                      timeout=120)
    assert bad.returncode != 0 and "expected some of" in bad.stdout + bad.stderr


def test_geometry_rows_say_whose_failure_it_is() -> None:
    """A station the strategy cannot calibrate even from the true H is not blamed on the
    start; a start outside the basin is marked NO."""
    from calstation.bench.targetless import geometry_markdown

    ok = {"param": "tz_mm", "value": 50.0, "scenario": "D5", "seed": 3004, "status": "ok",
          "tz_from_chord_m": 0.0556, "start_axis_offset_m": 0.005, "same": True,
          "axis_offset_m": 6e-5, "axis_angle_rad": math.radians(0.17)}
    off = {**ok, "param": "ry_deg", "value": 2.0, "same": False}
    beyond = {"param": "tz_mm", "value": 250.0, "scenario": "D5", "seed": 3004,
              "status": "station", "message": "even from the true H: no cells", "same": False}
    md = "\n".join(geometry_markdown([ok, off, beyond]))
    assert "| tz = +50 mm | 55.6 | 5.0 | yes | 0.060 / 0.170 |" in md
    assert "| ry +2° off nominal | 55.6 | 5.0 | NO |" in md
    assert "| tz = +250 mm | — | — | no: even from the true H: no cells | — |" in md
    assert geometry_markdown([]) == []
