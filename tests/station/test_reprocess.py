"""``calstation calibrate --run N``: re-processing a stored run from its own recordings and recipe.

The run is stored the way the station stores it (run, steps, artifacts with sha256, initial and
accepted fine calibrations) around real simulated recordings; the re-processing then runs the
real engine on them.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from calstation.engine.metrics import axis_errors
from calstation.pipeline import recording_disagreements
from calstation.recipes import load_recipe
from calstation.recordings.reader import read_recording
from calstation.recordings.runfolder import file_sha256
from calstation.storage.db import Artifact, Calibration, Database, Run, Station, Step, open_database
from tests.support.clirun import run_cli as _run

REPO = Path(__file__).resolve().parents[2]
RECIPE = REPO / "recipes" / "sim-periodicity.yaml"


def _store_run(db: Database, files: dict[str, Path], status: str = "passed",
               shape: dict[str, object] | None = None, range_model: str | None = None) -> int:
    """A finished periodicity run of ``files`` as the station stores it; returns its id.
    ``shape``: the recipe's ``calibration.options.shape``; ``range_model``: its
    ``calibration.range_model``."""
    from calstation.engine.initial import initial_calibration
    from calstation.recipes import LoadedRecipe, parse_recipe

    loaded = load_recipe(RECIPE)
    if shape is not None or range_model is not None:
        data = yaml.safe_load(loaded.text)
        if shape is not None:
            data["calibration"].setdefault("options", {})["shape"] = shape
        if range_model is not None:
            data["calibration"]["range_model"] = range_model
        text = yaml.safe_dump(data, sort_keys=False)
        loaded = LoadedRecipe(parse_recipe(text, str(RECIPE)), RECIPE, text)
    static = read_recording(files["static"])
    initial = initial_calibration(static, loaded.recipe.fixtures.static_target,
                                  loaded.recipe.calibration.initial).H.as_dict()
    truth = static.truth
    assert truth is not None
    fine = truth.with_(tx=truth.tx + 2e-4).as_dict()  # the run's accepted result, 0.2 mm off
    with db.session() as s:
        run = Run(station=Station(name="sim-01"), recipe_name=loaded.recipe.name,
                  recipe_path=str(RECIPE), recipe_text=loaded.text, recipe_sha256=loaded.sha256,
                  operator="ann", unattended=True, data_dir=str(files["static"].parent),
                  status=status)
        s.add(run)
        for name, kind in (("static_scan", "static"), ("spin_scan", "spin"),
                           ("cube_scan", "cube")):
            step = Step(run=run, name=name, status="passed",
                        result={"recording": str(files[kind]), "fixture": "spin_target"})
            s.add(step)
            s.flush()
            s.add(Artifact(run=run, step_id=step.id, kind=kind, path=str(files[kind]),
                           size_bytes=files[kind].stat().st_size,
                           sha256=file_sha256(files[kind])))
        s.add(Calibration(run=run, stage="initial", strategy="initial", **initial))
        s.add(Calibration(run=run, stage="fine", strategy="periodicity", **fine, cost=1e-7,
                          iterations=5, accepted=status == "passed"))
        s.flush()
        return run.id


def test_reprocessing_with_shape_stores_a_second_calibration(
    sim_run, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    files = sim_run()
    url = f"sqlite:///{tmp_path / 'qa.db'}"
    db = open_database(url)
    # the box cost alone: neither the known-size cube fit nor the range model it estimates
    run_id = _store_run(db, files, shape={"known_size": False}, range_model="none")

    code, out, err = _run(
        ["calibrate", "--run", str(run_id), "--strategy", "shape", "--db", url, "--json"], capsys
    )
    # at 1 mm of noise the box cost alone (the recipe turns the known-size cube fit off) does
    # not determine the axis to the recipe's budget: stored, refused
    assert code == 3, err
    data = json.loads(out)
    assert data["run_id"] == run_id and data["strategy"] == "shape"
    # the recordings were taken with the recipe before its shape option was changed: said so
    assert data["accepted"] is False
    assert all("the recipe text differs from the one of the scan" in w for w in data["warnings"])
    assert data["refused"] and any("calibration.accuracy.max_error" in r and "What would help"
                                   in r for r in data["refused"])
    assert "refused" in err and "not accepted" in err
    truth = read_recording(files["cube"]).truth
    assert truth is not None
    with db.session() as s:
        cals = s.query(Calibration).filter_by(run_id=run_id).order_by(Calibration.id).all()
        assert [(c.stage, c.strategy, c.accepted) for c in cals] == [
            ("initial", "initial", False), ("fine", "periodicity", True),
            ("reprocess", "shape", False)]
        new, fine = cals[2], cals[1]
        assert new.id == data["calibration_id"] and data["compared_to"] == fine.id
        # the shape strategy used the run's cube scan, and lands near the truth
        assert new.diagnostics["reprocess"]["recordings"]["cube"] == str(files["cube"])
        assert new.diagnostics["timings"]["total"] > 0
        from calstation.engine.frames import Extrinsics

        H = Extrinsics.from_dict(new.params())
        assert axis_errors(H, truth)["axis_offset_m"] < 3e-3  # shape: mm-level, not sub-mm
        for p in ("tx", "ty", "tz", "ry", "rz"):
            assert data["difference"][p] == pytest.approx(new.params()[p] - fine.params()[p])

    # show lists both calibrations: the accepted fine one and the re-processing
    code, out, _ = _run(["show", str(run_id), "--db", url, "--json"], capsys)
    summary = json.loads(out)
    assert [(c["stage"], c["accepted"]) for c in summary["calibrations"]] == [
        ("initial", False), ("fine", True), ("reprocess", False)]
    code, out, _ = _run(["show", str(run_id), "--db", url], capsys)
    assert code == 0 and "fine ✔" in out and "reprocess" in out and "shape" in out

    # --accept does not accept a refused result: the run keeps its accepted calibration
    code, out, err = _run(["calibrate", "--run", str(run_id), "--strategy", "shape", "--accept",
                           "--db", url], capsys)
    assert code == 3 and "not accepted although --accept was given" in " ".join(err.split())
    with db.session() as s:
        accepted = s.query(Calibration).filter_by(run_id=run_id, accepted=True).all()
        assert [c.id for c in accepted] == [fine.id]

    # the recipe's periodicity, with ry combined from the run's cube scan as at the station:
    # the text output prints the difference to the accepted calibration; --accept makes the
    # re-processing the run's only accepted calibration
    code, out, err = _run(["calibrate", "--run", str(run_id), "--accept", "--db", url], capsys)
    assert code == 0, err
    assert f"difference to the accepted calibration {fine.id}" in out
    assert "(re-processing, accepted)" in out and "nan" not in out
    with db.session() as s:
        accepted = s.query(Calibration).filter_by(run_id=run_id, accepted=True).all()
        assert len(accepted) == 1 and accepted[0].stage == "reprocess"
        assert accepted[0].id > new.id and accepted[0].strategy == "periodicity+cube"
        assert accepted[0].diagnostics["reprocess"]["recordings"]["cube"] == str(files["cube"])
    db.dispose()


def test_reprocessing_with_shape_and_its_known_size_cube_meets_the_budget(
    sim_run, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """With the recipe's default shape options the known-size cube fit places the axis to a
    few hundredths of a millimetre: the re-processing is within the budget, and --accept makes
    it the run's accepted calibration."""
    files = sim_run()
    url = f"sqlite:///{tmp_path / 'qa.db'}"
    db = open_database(url)
    run_id = _store_run(db, files)
    code, out, err = _run(["calibrate", "--run", str(run_id), "--strategy", "shape", "--accept",
                           "--db", url, "--json"], capsys)
    assert code == 0, err
    data = json.loads(out)
    assert data["strategy"] == "shape" and data["refused"] == [] and data["accepted"] is True
    truth = read_recording(files["cube"]).truth
    assert truth is not None
    with db.session() as s:
        accepted = s.query(Calibration).filter_by(run_id=run_id, accepted=True).one()
        assert accepted.stage == "reprocess" and accepted.strategy == "shape"
        assert accepted.diagnostics["known_size"]["used"] is True
        from calstation.engine.frames import Extrinsics

        e = axis_errors(Extrinsics.from_dict(accepted.params()), truth)
        assert e["axis_offset_m"] < 0.15e-3
        assert accepted.predicted_error_m is not None and accepted.predicted_error_m <= 0.0003
    db.dispose()


def test_reprocessing_refuses_a_changed_recording_and_bad_arguments(
    sim_run, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    files = sim_run()
    url = f"sqlite:///{tmp_path / 'qa.db'}"
    db = open_database(url)
    run_id = _store_run(db, files, status="failed")
    with db.session() as s:
        art = s.query(Artifact).filter_by(run_id=run_id, kind="cube").one()
        art.sha256 = "0" * 64
    db.dispose()
    code, _, err = _run(["calibrate", "--run", str(run_id), "--strategy", "shape", "--db", url],
                        capsys)
    assert code == 2 and "changed since it was stored" in err and "000000000000" in err
    code, _, err = _run(["calibrate", "--run", str(run_id), "--accept", "--db", url], capsys)
    assert code == 2 and "status failed" in err and "--accept" in err
    code, _, err = _run(["calibrate", "--run", "999", "--db", url], capsys)
    assert code == 2 and "no run with id 999" in err
    code, _, err = _run(["calibrate", str(RECIPE), "--run", str(run_id), "--db", url], capsys)
    assert code == 2 and "either" in err
    code, _, err = _run(["calibrate", str(RECIPE), "--static", str(files["static"])], capsys)
    assert code == 2 and "missing --spin" in err and "Traceback" not in err


def test_recipe_and_recording_disagreements_name_both_values(sim_run, tmp_path: Path) -> None:
    files = sim_run()
    data = yaml.safe_load(RECIPE.read_text(encoding="utf-8"))
    data["station"]["encoder"]["direction"] = -1
    data["station"]["encoder"]["ppr"] = 2048
    path = tmp_path / "other.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    other = load_recipe(path)
    warnings = recording_disagreements(read_recording(files["static"]), other)
    assert len(warnings) == 3, warnings
    direction, counts, sha = warnings
    assert "+1 in the recording" in direction and "-1 in the recipe" in direction
    assert "4096 encoder counts per revolution in the recording" in counts
    assert "8192 in the recipe" in counts
    recorded = read_recording(files["static"]).metadata["calstation"]["recipe_sha256"]
    assert recorded[:12] in sha and other.sha256[:12] in sha
    assert recording_disagreements(read_recording(files["static"]), load_recipe(RECIPE)) == []


def test_calibrate_files_warns_on_a_disagreeing_recipe(
    sim_run, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    files = sim_run()
    data = yaml.safe_load(RECIPE.read_text(encoding="utf-8"))
    data["station"]["encoder"]["direction"] = -1
    # this test is about the warnings: shape's predicted error at 1 mm of noise and one turn is
    # over the default budget
    data["calibration"]["accuracy"] = {"max_error": 0.005}
    path = tmp_path / "reversed.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    code, out, err = _run(["calibrate", str(path), "--static", str(files["static"]),
                           "--spin", str(files["cube"]), "--strategy", "shape"], capsys)
    assert code == 0, err
    assert "warning:" in err and "-1 in the recipe" in err and "+1 in the recording" in err
    assert "nan" not in out and " s" in out
