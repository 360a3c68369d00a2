"""Runs stored as the station stores them (rows only, values chosen to be non-round), for the
tests of the QA commands and of what they print."""

from __future__ import annotations

import datetime as dt

from calstation.storage.db import (
    Artifact,
    Calibration,
    CubeCheckRecord,
    Database,
    Run,
    Station,
    Step,
)
from tests.support.paths import RECIPES

RECIPE = RECIPES / "sim-periodicity.yaml"


def add_run(
    db: Database, station: str, status: str, H: dict[str, float], started: dt.datetime,
    edge_error: float = 0.0004, recipe_text: str | None = None, serial: str | None = None,
    error: str | None = None, operator: str = "qa",
) -> int:
    """One run as the station stores it (rows only; values chosen to be non-round)."""
    text = recipe_text or RECIPE.read_text(encoding="utf-8")
    with db.session() as s:
        st = s.query(Station).filter_by(name=station).one_or_none() or Station(name=station)
        run = Run(station=st, recipe_name="sim-periodicity", recipe_path=str(RECIPE),
                  recipe_text=text, recipe_sha256="ab" * 32, operator=operator, unattended=True,
                  data_dir="/data/runs/x", status=status, started_at=started,
                  unit_serial=serial, error=error,
                  finished_at=started + dt.timedelta(minutes=3))
        step = Step(run=run, name="static_scan", status="passed", result={"lines": 100})
        s.add_all([run, step])
        s.flush()
        s.add(Calibration(run=run, step_id=step.id, stage="initial", strategy="initial",
                          **{k: v + 1e-4 for k, v in H.items()}, sigma_tx=2.5e-5, cost=0.1,
                          iterations=1, diagnostics={"segments": 2}))
        s.add(Calibration(run=run, stage="fine", strategy="periodicity", **H,
                          sigma_tx=1.234567e-5, sigma_ty=None, sigma_tz=3.3e-5, sigma_rx=None,
                          sigma_ry=7.1e-4, sigma_rz=1.9e-5, cost=3.14159e-7, iterations=9,
                          accepted=status == "passed",
                          diagnostics={"matches": [1200, 1310], "gauge": "platter"}))
        s.add(CubeCheckRecord(run=run, obb_edges=[0.1012, 0.1009, 0.1003], obb_error=0.0012,
                              face_edges=[0.10004, 0.09998, 0.10003], edge_error=edge_error,
                              flatness_rms=0.00091, perpendicularity_deg=0.05,
                              passed=edge_error < 0.001, failures=[]))
        s.add(Artifact(run=run, step_id=step.id, kind="static", path="/data/runs/x/static.mcap",
                       size_bytes=123456789, sha256="cd" * 32))
        s.flush()
        return run.id


H1 = {"tx": 0.0123456789012345, "ty": 1.2498765432101234, "tz": -0.0004321098765432,
      "rx": 0.0, "ry": 0.0012345678901234, "rz": -0.7856781234567891}
