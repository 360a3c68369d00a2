"""The one calibration pipeline (calstation.pipeline): the station, ``calibrate --run N`` and a
``reprocess`` campaign make the same calibration of the same recordings, to the last bit; a spin
scan prepared while it was taken serves a cut of it as its file would."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from sqlalchemy import select

from calstation.storage.db import Calibration, Run, Step, open_database
from tests.support.clirun import run_cli
from tests.support.recordings import fed_builder

pytest.importorskip("calstation_sim")

RECIPES = Path(__file__).resolve().parents[2] / "recipes"


def _quick_both_ways(tmp_path: Path) -> Path:
    """The simulated station turning both ways (every stage of the pipeline runs: the strategy,
    ry with the cube, the time offset), made quick: 500 points per line at 60 rpm, a budget the
    first turn meets (the spin scan stops on a fit made while it was taken)."""
    data = yaml.safe_load((RECIPES / "sim-periodicity-both-ways.yaml").read_text())
    data["simulation"]["lidar"]["points_per_line"] = 500
    data["simulation"]["seed"] = 5
    turning = {"rpm": 60, "revolutions": 1.02, "settle_s": 0.1, "second_pass_rpm": -60}
    data["steps"] = {"static_scan": {"lines": 40},
                     "spin_scan": {**turning, "max_revolutions": 3},
                     "cube_scan": {**turning, "max_revolutions": 1.02}}
    data["calibration"] = {"strategy": "periodicity", "accuracy": {"max_error": 0.005}}
    path = tmp_path / "both-ways.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _stored(c: Calibration) -> dict[str, Any]:
    """What must be identical: H, σ, the time offset and its σ, the strategy."""
    return {"H": c.params(), "sigma": c.sigmas(), "latency": c.encoder_latency_s,
            "sigma_latency": c.sigma_encoder_latency_s, "strategy": c.strategy}


def test_the_station_calibrate_run_and_reprocess_give_the_same_h_bit_for_bit(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("CALSTATION_HOME", str(tmp_path / "home"))
    url = f"sqlite:///{tmp_path / 'runs.db'}"
    code, out, err = run_cli(["run", str(_quick_both_ways(tmp_path)), "--yes", "--db", url],
                             capsys)
    assert code == 0 and "PASS" in out, out[-2000:] + err[-2000:]
    db = open_database(url)
    try:
        with db.session() as s:
            (run,) = s.scalars(select(Run)).all()
            (station,) = s.scalars(select(Calibration).where(Calibration.accepted)).all()
            spin = s.scalars(select(Step).where(Step.name == "spin_scan")).one().result
            station_made = _stored(station)
        # every stage ran at the station: a fit made while scanning, ry with the cube's faces,
        # the time offset from the second pass
        assert spin["turn_by_turn"]["stopped"] == "budget"
        assert station_made["strategy"] == "periodicity+cube"
        assert station_made["latency"] is not None

        code, out, err = run_cli(["calibrate", "--run", str(run.id), "--db", url, "--json"],
                                 capsys)
        assert code == 0, err
        assert json.loads(out)["refused"] == []
        code, out, err = run_cli(["reprocess", "--db", url, "--workers", "1", "--json"], capsys)
        assert code == 0, err
        with db.session() as s:
            again = s.scalars(select(Calibration).where(Calibration.stage == "reprocess")
                              .order_by(Calibration.id)).all()
            remade = [_stored(c) for c in again]
        assert len(remade) == 2  # calibrate --run, then the campaign
        for made in remade:
            assert made == station_made  # exactly: ==, not approximately
    finally:
        db.dispose()


def test_a_scan_prepared_while_taken_serves_its_first_lines_as_the_file_does(sim_run) -> None:
    """The station cuts a scan that stopped on a fit to the lines that fit saw; its preparation
    made while scanning then gives what preparing the cut recording gives, bit for bit."""
    from calstation.pipeline import turned
    from calstation.recordings.reader import read_recording

    rec = read_recording(sim_run()["spin"])
    builder = fed_builder(rec)
    # the whole scan: the builder's own preparation, not one made again from the file
    assert turned(rec, builder=builder).prepared is builder.finish()
    lines = rec.n_lines * 2 // 3
    live = turned(rec, fitted=(1, lines), builder=builder)
    read = turned(rec, fitted=(1, lines))
    assert live.recording is not None and live.recording.n_lines == lines
    assert live.whole is rec and live.whole_prepared is builder.finish()
    assert read.whole is rec and read.whole_prepared is None
    assert 0 < live.prepared.n_points < builder.finish().n_points
    for name in ("p_L", "phi", "rng", "az"):
        assert np.array_equal(getattr(live.prepared, name), getattr(read.prepared, name)), name
    assert np.array_equal(live.prepared.static, read.prepared.static)
    assert live.prepared.noise == read.prepared.noise
    # a preparation of other lines is not taken for this recording's
    other = turned(rec.first_lines(lines), builder=builder)
    assert other.prepared is not builder.finish()
