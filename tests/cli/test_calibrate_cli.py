"""``calstation calibrate`` and ``calstation verify`` on simulated recordings (real files)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from calstation.engine.metrics import axis_errors
from calstation.engine.result import CalibrationResult
from calstation.recordings.reader import read_recording
from tests.support.clirun import run_cli as _run

RECIPE = str(Path(__file__).resolve().parents[2] / "recipes" / "sim-periodicity.yaml")


def test_calibrate_json_then_verify(sim_run, tmp_path, capsys) -> None:
    run = sim_run()
    calib = tmp_path / "calib.yaml"
    argv = ["calibrate", RECIPE, "--static", str(run["static"]), "--spin", str(run["spin"])]
    # the spin target alone cannot measure the lidar's range offset: refused, saying so
    code, out, _ = _run([*argv, "--json"], capsys)
    assert code == 3 and any("range offset" in r and "QA cube" in r
                             for r in json.loads(out)["refused"])
    argv += ["--cube", str(run["cube"])]
    code, out, _ = _run([*argv, "--out", str(calib), "--json"], capsys)
    assert code == 0
    data = json.loads(out)
    for key in ("tx", "ty", "tz", "rx", "ry", "rz", "strategy", "cost"):
        assert key in data
    for n in ("tx", "ty", "tz", "ry", "rz"):
        assert data[f"sigma_{n}"] > 0
    assert data["strategy"] == "periodicity+cube" and data["sigma_rx"] is None
    saved = CalibrationResult.load(calib)
    assert saved.H.tx == pytest.approx(data["tx"]) and saved.strategy == "periodicity+cube"
    assert saved.range_offset == pytest.approx(data["range_offset"])
    truth = read_recording(run["spin"]).truth
    assert truth is not None
    assert axis_errors(saved.H, truth)["axis_offset_m"] < 0.5e-3

    code, out, _ = _run(
        ["verify", RECIPE, "--cube", str(run["cube"]), "--calibration", str(calib), "--json"],
        capsys,
    )
    check = json.loads(out)
    assert code == 0 and check["passed"] is True
    assert all(abs(e - 0.1) < 0.5e-3 for e in check["face_edges_m"])

    # a calibration 1° off in rz fails the check with exit code 1
    bad = saved.H.with_(rz=saved.H.rz + math.radians(1.0))
    bad_file = tmp_path / "bad.json"
    CalibrationResult(bad, saved.sigma, 0.0, 0, "manual").save(bad_file)
    code, out, _ = _run(
        ["verify", RECIPE, "--cube", str(run["cube"]), "--calibration", str(bad_file)], capsys
    )
    assert code == 1 and "FAIL" in out


def test_errors_are_clean_messages(sim_run, tmp_path, capsys) -> None:
    run = sim_run()
    code, _, err = _run(
        ["calibrate", RECIPE, "--static", str(tmp_path / "none.mcap"), "--spin", str(run["spin"])],
        capsys,
    )
    assert code == 2 and "error:" in err and "none.mcap" in err and "Traceback" not in err
    code, _, err = _run(
        [
            "calibrate",
            RECIPE,
            "--static",
            str(run["static"]),
            "--spin",
            str(run["spin"]),
            "--strategy",
            "nonsense",
        ],
        capsys,
    )
    assert code == 2 and "nonsense" in err and "periodicity" in err
    # the spin scan given as the static scan: no L-target, a clear error
    code, _, err = _run(
        ["calibrate", RECIPE, "--static", str(run["cube"]), "--spin", str(run["spin"])], capsys
    )
    assert code == 2 and "error:" in err


def test_calibrate_with_the_cube_combines_ry(sim_run, tmp_path, capsys) -> None:
    run = sim_run()
    argv = ["calibrate", RECIPE, "--static", str(run["static"]), "--spin", str(run["spin"])]
    saved = tmp_path / "joint.json"
    code, out, err = _run([*argv, "--cube", str(run["cube"]), "--json", "--out", str(saved)],
                          capsys)
    assert code == 0, err
    both = json.loads(out)
    assert both["strategy"] == "periodicity+cube" and "side-face twist" in err
    # the cube's faces add to ry: the combined σ is smaller, and it covers the real error
    joint = CalibrationResult.load(saved).diagnostics["joint"]
    assert both["sigma_ry"] < joint["spin_target"]["sigma"]["ry"]
    assert both["sigma_ry"] < joint["cube"]["sigma"]["ry"]
    truth = read_recording(run["spin"]).truth
    assert truth is not None
    assert abs(both["ry"] - truth.ry) <= 3 * both["sigma_ry"]
    # and the lidar's range offset (none on the simulator) is measured, within its σ
    assert abs(both["range_offset"]) <= 3 * both["sigma_range_offset"]
    assert both["sigma_range_offset"] < 0.3e-3 and both["range_scale"] is None

    # the wrong recording, or a strategy that already fine-tunes on the cube: a clear message
    code, _, err = _run([*argv, "--cube", str(run["spin"])], capsys)
    assert code != 0 and "not a scan of the QA cube" in err and "Traceback" not in err
    shape = ["calibrate", RECIPE, "--static", str(run["static"]), "--spin", str(run["cube"]),
             "--strategy", "shape", "--cube", str(run["cube"])]
    code, _, err = _run(shape, capsys)
    assert code != 0 and "give the cube scan as --spin" in err
