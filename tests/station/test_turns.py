"""Scanning until the accuracy budget holds (calstation.station.turns), on the simulated
station: the spin scan goes on turn by turn while the predicted error is above the budget, the
fine-tuning takes or redoes the fit, and a refusal says what would help."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
import yaml

from calstation.recipes import load_recipe
from calstation.station.reprocess import compute_reprocessing, plan_reprocessing
from calstation.station.runs import start_run
from calstation.storage.db import Calibration, Database, Run
from tests.support.recordings import fed_builder
from tests.support.station import UnattendedOperator, last_step, whole_turns

pytest.importorskip("calstation_sim")

RECIPES = Path(__file__).resolve().parents[2] / "recipes"


def _recipe(tmp_path: Path, budget: float, range_model: str = "offset", **spin: Any) -> Path:
    """The simulated station made quick: 500 points per line at 60 rpm."""
    data = yaml.safe_load((RECIPES / "sim-periodicity.yaml").read_text())
    data["simulation"]["lidar"]["points_per_line"] = 500
    data["simulation"]["seed"] = 3
    data["steps"] = {"static_scan": {"lines": 40},
                     "spin_scan": {"rpm": 60, "revolutions": 1.02, "settle_s": 0.1, **spin},
                     "cube_scan": {"rpm": 60, "revolutions": 1.02, "settle_s": 0.1,
                                   "max_revolutions": 1.02}}
    data["calibration"] = {"accuracy": {"max_error": budget}, "range_model": range_model}
    # the simulated platter and cube read alike (offset+scale needs them to)
    data["fixtures"]["qa_cube"]["same_finish_as_platter"] = True
    path = tmp_path / "turns.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def test_a_generous_budget_ends_the_spin_scan_after_its_first_fit(
    tmp_path: Path, db: Database
) -> None:
    ui = UnattendedOperator()
    run_id, status = start_run(load_recipe(_recipe(tmp_path, 0.005)), db, ui,
                               operator="t", data_dir=tmp_path)
    assert status == "passed", ui.failures
    spin = last_step(db, run_id, "spin_scan").result
    summary = spin["turn_by_turn"]
    # the first fit (one turn) met the budget and ended the scan, well before its 8 turns
    assert summary["stopped"] == "budget"
    assert summary["fits"][0]["turns"] == 1
    assert summary["fits"][-1]["predicted_error_m"] <= 0.005
    assert whole_turns(spin["recording"]) < 8
    accuracy = [e for e in ui.events if e.kind == "accuracy"]
    assert accuracy and accuracy[0].data["turns"] == 1 and accuracy[0].data["budget_m"] == 0.005
    fine = last_step(db, run_id, "fine_tune").result
    assert fine["predicted_error_m"] <= fine["budget_m"] == 0.005
    with db.session() as s:
        accepted = s.query(Calibration).filter_by(run_id=run_id, accepted=True).one()
        assert accepted.predicted_error_m is not None and accepted.predicted_error_m <= 0.005
        assert accepted.diagnostics["predicted_error"]["budget_m"] == 0.005
        stored = accepted.params()
        run = s.get(Run, run_id)
        assert run is not None
        job = plan_reprocessing(run)
    # re-processed, the run gives what the station stored: the fit on the turns that met the
    # budget, not on the turns scanned while it was computed
    assert job.turns == {"spin": 1.0}
    again = compute_reprocessing(job).result.H.as_dict()
    for name, value in stored.items():
        assert again[name] == pytest.approx(value, abs=1e-9), (name, again, stored)


@pytest.mark.parametrize("range_model", ["none", "offset"])
def test_an_unreachable_budget_turns_to_the_maximum_and_is_refused_with_what_would_help(
    tmp_path: Path, db: Database, range_model: str
) -> None:
    ui = UnattendedOperator()
    run_id, status = start_run(
        load_recipe(_recipe(tmp_path, 0.00005, range_model, max_revolutions=3)), db, ui,
        operator="t", data_dir=tmp_path,
    )
    assert status == "failed"
    spin = last_step(db, run_id, "spin_scan").result
    summary = spin["turn_by_turn"]
    assert summary["stopped"] == "turns" and summary["max_revolutions"] == 3
    assert whole_turns(spin["recording"]) == 3  # the recording holds every turn
    assert [f["turns"] for f in summary["fits"]] == sorted({f["turns"] for f in summary["fits"]})
    (step, error), = ui.failures
    assert "calibration.accuracy.max_error" in error and "What would help" in error
    # with the range model too: the spin target's own σ (its range terms and ty held for the
    # cube) is over the budget, and the spin scan is told what would help
    assert step == "fine_tune", error
    # every suggestion is computed from this scan: more turns (how many), a slower platter, a
    # faster line rate, each with its number
    assert "turns (steps.spin_scan.max_revolutions:" in error and "this scan took 3" in error
    assert "rpm instead of 60" in error and "lines/s instead of 1000" in error
    refused = json.loads(json.dumps(last_step(db, run_id, "fine_tune").result))
    assert refused["refused"]["predicted_error_m"] > 0.00005


def test_with_the_range_model_the_cube_scan_turns_until_the_combination_meets_the_budget(
    tmp_path: Path, db: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The spin target alone meets the budget with the range terms held; the cube that measures
    them does not after one turn at 2 mm of noise (0.40 mm against 0.37), so the cube scan goes
    on until the combination is within, and the run is accepted within 3σ of the true H. The
    cube step takes the stage the fit within the budget made while the scan turned: the spin
    target is fitted again from the combination only in the fits' thread, never after the
    scan, and the cube step does not read the cube's recording back (the wait after the
    scan). Each fit keeps what it computed in a memo of its own, not in the scan so far."""
    import math
    import threading

    import calstation.recordings.reader as reader
    from calstation.plugins.cost_strategies import PeriodicityStrategy
    from calstation.recordings.reader import read_recording
    from calstation.station.steps.cube_scan import CubeScan
    from calstation.station.turns import TurnByTurn

    refits: list[str] = []
    refit = PeriodicityStrategy.refit

    def counted(self: PeriodicityStrategy, *args: Any, **kwargs: Any) -> Any:
        refits.append(threading.current_thread().name)
        return refit(self, *args, **kwargs)

    step: list[str] = []  # the cube step while it runs
    reads: list[tuple[str, str]] = []  # the recordings it read (not the fits' thread)
    step_run = CubeScan.run

    def stepped(self: CubeScan, *args: Any) -> Any:
        step.append("cube_scan")
        try:
            return step_run(self, *args)
        finally:
            step.clear()

    def read(path: str | Path) -> Any:
        if step and threading.current_thread() is threading.main_thread():
            reads.append(Path(path).name)
        return read_recording(path)

    fitted: list[Any] = []  # the cube's scans so far each turn's fit was handed
    turn_fit = TurnByTurn._fit

    def handed(self: TurnByTurn, scan: Any, *args: Any) -> Any:
        out = turn_fit(self, scan, *args)
        if self.scan == "cube_scan":
            fitted.append(scan)
        return out

    monkeypatch.setattr(PeriodicityStrategy, "refit", counted)
    monkeypatch.setattr(CubeScan, "run", stepped)
    monkeypatch.setattr(reader, "read_recording", read)
    monkeypatch.setattr(TurnByTurn, "_fit", handed)

    path = _recipe(tmp_path, 0.00037)
    data = yaml.safe_load(path.read_text())
    data["steps"]["cube_scan"]["max_revolutions"] = 4
    data["simulation"]["lidar"]["range_noise"] = 0.002
    data["calibration"]["accuracy"]["axis_sigma"] = None  # the budget alone (next test)
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    ui = UnattendedOperator()
    run_id, status = start_run(load_recipe(path), db, ui, operator="t", data_dir=tmp_path)
    assert status == "passed", ui.failures
    fine = last_step(db, run_id, "fine_tune").result
    assert fine["predicted_error_m"] <= 0.00037
    cube = last_step(db, run_id, "cube_scan").result
    fits = cube["turn_by_turn"]["fits"]
    assert cube["turn_by_turn"]["stopped"] == "budget"
    assert fits[0]["predicted_error_m"] > 0.00037 >= fits[-1]["predicted_error_m"]
    assert len(fits) >= 2
    assert refits and all(name.startswith("calstation-cube_scan-fit") for name in refits), refits
    assert "cube.mcap" not in reads, reads
    # each fit's stage keeps what it computed (corrected returns, segmentations) in a memo of
    # its own, not in the scan so far, which the builder keeps with every turn (eight turns at
    # 1000 lines/s held 11 GB)
    assert len(fitted) >= 2 and all(not scan.memo for scan in fitted), [
        sorted(scan.memo) for scan in fitted]
    truth = read_recording(Path(cube["recording"])).truth
    assert truth is not None
    with db.session() as s:
        accepted = s.query(Calibration).filter_by(run_id=run_id, accepted=True).one()
        assert accepted.predicted_error_m is not None and accepted.predicted_error_m <= 0.00037
        assert accepted.range_offset is not None
        params, sigma = accepted.params(), accepted.result().sigma
        turns = accepted.diagnostics["predicted_error"]["turns"]
        run = s.get(Run, run_id)
        assert run is not None
        job = plan_reprocessing(run)
    assert turns == len(fits) == job.turns["cube"], (turns, fits, job.turns)
    for name in ("tx", "ty", "tz", "ry", "rz"):
        error = params[name] - getattr(truth, name)
        assert not math.isnan(sigma[name]) and abs(error) <= 3 * sigma[name], (name, error)
    # the step combined the cube's fit made while it turned; re-processed from the recordings
    # (the fit made anew on the lines that met the budget) the run gives the same H
    again = compute_reprocessing(job).result
    assert again.range_offset == accepted.range_offset
    for name, value in params.items():
        assert again.H.as_dict()[name] == pytest.approx(value, abs=1e-12), name


@pytest.mark.parametrize("limit", [0.00013, 0.00006])
def test_with_the_range_model_the_cube_scan_turns_on_while_it_places_the_axis(
    tmp_path: Path, db: Database, limit: float
) -> None:
    """A generous budget is met by the first cube turn, but the cube's size, which sets the
    range offset and scale and with them where H puts the axis, leaves the axis's position σ
    above calibration.accuracy.axis_sigma: the scan turns on until it is within (0.13 mm, after
    3 turns on this scene), or until the σ's fall over the turns says the turns left cannot
    bring it there (0.06 mm: it levels off at about 0.07 mm). Either way the axis found is
    within 3 of its σ of the true one."""
    import numpy as np

    from calstation.engine.accuracy import axis_offset_sigma
    from calstation.recordings.reader import read_recording

    path = _recipe(tmp_path, 0.005, "offset+scale")
    data = yaml.safe_load(path.read_text())
    data["steps"]["cube_scan"]["max_revolutions"] = 6
    data["calibration"]["accuracy"]["axis_sigma"] = limit
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    ui = UnattendedOperator()
    run_id, status = start_run(load_recipe(path), db, ui, operator="t", data_dir=tmp_path)
    assert status == "passed", ui.failures
    told = "\n".join(m for m in ui.messages if "turn" in m)
    summary = last_step(db, run_id, "cube_scan").result["turn_by_turn"]
    fits = summary["fits"]
    assert summary["stopped"] == "budget", told
    assert fits[0]["predicted_error_m"] <= 0.005 and 2 <= len(fits) < 6, told
    assert "turning on: the axis's position σ" in told
    with db.session() as s:
        result = s.query(Calibration).filter_by(run_id=run_id, accepted=True).one().result()
    sigma = axis_offset_sigma(result.H, result.diagnostics["covariance"])
    if limit > 0.0001:
        assert sigma <= limit, told
    else:
        assert sigma > limit and "would not bring it within (it levels off at" in told, told
    cube = last_step(db, run_id, "cube_scan").result
    truth = read_recording(Path(cube["recording"])).truth
    assert truth is not None
    axis = truth.axis_direction()
    across = np.eye(3) - np.outer(axis, axis)
    assert np.linalg.norm(across @ (result.H.t - truth.t)) <= 3 * sigma


def test_exactly_the_asked_turns_without_turn_by_turn(tmp_path: Path, db: Database) -> None:
    ui = UnattendedOperator()
    run_id, status = start_run(
        load_recipe(_recipe(tmp_path, 1e-6, max_revolutions=1.02)), db, ui, operator="t",
        data_dir=tmp_path,
    )
    spin = last_step(db, run_id, "spin_scan").result
    assert "turn_by_turn" not in spin and whole_turns(spin["recording"]) == 1
    assert not [e for e in ui.events if e.kind == "accuracy"]
    assert status == "failed"


def test_a_cube_fits_noise_bias_over_the_budget_is_told_what_would_help() -> None:
    """At 2 mm of range noise the cube faces' bias in ry (0.08°, which the shape strategy's
    known-size fit declares) alone exceeds a 0.1 mm budget: more turns cannot help, and the
    advice is about the cube's sensor and strategy, not the spin target the recipe never
    scans."""
    import math

    from calstation.engine.frames import Extrinsics
    from calstation.engine.result import CalibrationResult
    from calstation.pipeline.judgement import budget_failure, with_prediction

    recipe = load_recipe(RECIPES / "sim-shape.yaml").recipe
    recipe = recipe.model_copy(update={"calibration": recipe.calibration.model_copy(
        update={"accuracy": recipe.calibration.accuracy.model_copy(update={"max_error": 1e-4})})})
    H = Extrinsics(0.0, 1.5, 0.0, 0.0, 0.0, math.radians(-30.0))
    sigma = {"tx": 2e-5, "ty": math.nan, "tz": 2e-5, "rx": math.nan,
             "ry": math.radians(0.081), "rz": math.radians(0.004)}
    result = CalibrationResult(H=H, sigma=sigma, cost=0.0, iterations=1, strategy="shape",
                               timings={}, diagnostics={"bias_bound": {"ry": math.radians(0.08)},
                                                        "range_noise_m": 0.002})
    result, predicted = with_prediction(result, recipe, turns=1)
    assert predicted.bias_m > 1e-4
    error = budget_failure(result, predicted, recipe, scan="spin_scan", turns=1)
    assert error is not None and "more data cannot help" in error
    assert "about 1.0 mm of range noise instead of 2.0 mm" in error
    assert "the spin target with the periodicity strategy" in error
    assert "taller" not in error and "off-centre" not in error
    # the same for a periodicity recipe speaks of its spin target
    spin = load_recipe(RECIPES / "sim-periodicity.yaml").recipe
    spin = spin.model_copy(update={"calibration": spin.calibration.model_copy(
        update={"accuracy": spin.calibration.accuracy.model_copy(update={"max_error": 1e-4})})})
    result, predicted = with_prediction(result, spin, turns=1)
    error = budget_failure(result, predicted, spin, scan="spin_scan", turns=1)
    assert error is not None and "taller, off-centre" in error


def test_a_fit_that_says_more_turns_would_not_help_stops_the_scan(sim_run: Any) -> None:
    """Two fixtures that disagree beyond chance do not agree after more turns: the fit says so
    (NoMoreTurns), the scan stops at once, and the step works on every whole turn (no fit is
    kept) and is told why."""
    from calstation.engine.spinscan import SpinScan
    from calstation.recordings.reader import read_recording
    from calstation.station.turns import NoMoreTurns, TurnByTurn, turns_fitted

    builder = fed_builder(read_recording(sim_run()["spin"]))
    seen: list[int] = []

    def fit(so_far: SpinScan) -> Any:
        seen.append(so_far.n_points)
        raise NoMoreTurns("the spin target and the QA cube disagree on the calibration")

    ui = UnattendedOperator()
    controller = TurnByTurn(builder, fit, budget_m=1e-3, max_revolutions=8,
                            max_duration_s=None, ui=ui, scan="cube_scan")
    assert controller(1.0, 3.0)  # the first whole turn: its fit is queued, the scan goes on
    turns = controller.close(1)
    assert len(seen) == 1 and seen[0] > 0
    assert turns.fit is None and turns.summary["stopped"] == "fit"
    assert turns_fitted(turns.summary) is None  # the step takes every whole turn
    assert "disagree" in turns.summary["failed_fits"][0]
    assert any("more turns would not change it" in m for m in ui.messages)
    assert not controller(1.5, 4.5)  # and would not turn on


class _Lines:
    """The builder side of a scan under way, as the turn-by-turn controller reads it."""

    def __init__(self) -> None:
        self.lines_ready = 0

    def so_far(self) -> object:
        return object()


def test_turning_on_for_more_never_costs_the_budget() -> None:
    """A fit within the budget for which ``more`` asks for more turns is kept: when the next
    fit is above the budget the scan ends on it, and the stored summary says so, so that the
    step after the scan and a re-processing take the same turns."""
    import time

    import numpy as np

    from calstation.engine.accuracy import PredictedError
    from calstation.engine.frames import Extrinsics
    from calstation.engine.result import CalibrationResult
    from calstation.station.turns import TurnByTurn, turns_fitted

    errors = {1: 0.0002, 2: 0.0004, 3: 0.0001}
    told: list[int] = []

    def fit(scan: object) -> tuple[CalibrationResult, PredictedError, None]:
        turns = len(told) + 1
        told.append(turns)
        predicted = PredictedError(errors[turns], errors[turns], 0.0, 0.95, np.zeros((0, 3)),
                                   np.zeros(0), ())
        return (CalibrationResult(H=Extrinsics(), sigma={}, cost=0.0, iterations=0,
                                  strategy="periodicity"), predicted, None)

    lines = _Lines()
    ui = UnattendedOperator()
    controller = TurnByTurn(lines, fit, budget_m=0.0003, max_revolutions=8, max_duration_s=None,
                            ui=ui, scan="cube_scan", more=lambda f: "the axis")
    for turn in (1, 2):
        lines.lines_ready = 100 * turn
        assert controller(float(turn), float(turn))
    # the scan goes on (no third fit is asked) until the second fit, above the budget, ends it
    give_up = time.monotonic() + 120.0  # a bound on a failure, not a wait: it ends on the fit
    while controller(2.5, 2.5):
        assert time.monotonic() < give_up, "the scan did not end on the kept fit"
    assert told == [1, 2]
    done = controller.close(2)
    assert done.fit is not None and done.fit.turns == 1 and done.fit.lines == 100
    assert done.summary["stopped"] == "budget" and done.summary["met_turns"] == 1
    assert [f["turns"] for f in done.summary["fits"]] == [1, 2]
    assert turns_fitted(done.summary) == (1, 100)
    assert any("the scan ends on the fit after 1 turn, within the budget" in m
               for m in ui.messages)
    # a summary stored before the kept fit was recorded ends its fits with the one it met
    old = {k: v for k, v in done.summary.items() if k != "met_turns"}
    assert turns_fitted(old) == (2, 200)


def test_a_simulated_run_is_the_same_from_the_same_seed_whatever_the_host_load(
    tmp_path: Path, db: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    """On the simulator's clock the lidar runs as fast as the host computes it: the turn fits
    are paced (each taken at the turn after the one it fitted), so how fast they run, and so
    how many lines each scan takes, does not depend on the host. Two runs of one recipe, one of
    them with the fits slowed down, give the same scans and the same H to the last bit."""
    import time as clock

    from calstation.station import turns

    path = _recipe(tmp_path, 0.005, "offset")
    data = yaml.safe_load(path.read_text())
    data["steps"]["cube_scan"]["max_revolutions"] = 4
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    fit = turns.TurnByTurn._fit
    seen = []
    for slow in (0.0, 0.5):

        def slowed(self: Any, *args: Any, _slow: float = slow) -> Any:
            clock.sleep(_slow)  # a loaded host: the fit ends later in the host's time
            return fit(self, *args)

        monkeypatch.setattr(turns.TurnByTurn, "_fit", slowed)
        ui = UnattendedOperator()
        run_id, status = start_run(load_recipe(path), db, ui, operator="t",
                                   data_dir=tmp_path / f"slow{slow}")
        assert status == "passed", ui.failures
        scans = {name: {k: v for k, v in (last_step(db, run_id, name).result["turn_by_turn"]
                                          or {}).items() if k != "fits"}
                 for name in ("spin_scan", "cube_scan")}
        with db.session() as s:
            accepted = s.query(Calibration).filter_by(run_id=run_id, accepted=True).one()
            seen.append((scans, accepted.params(), accepted.range_offset))
    assert seen[0] == seen[1]
