"""Web stations starting runs at once, under load: every run reaches its first prompt.

Each trial is a fresh process (tests/support/stress_starts.py) in which four web stations over one
database start a run at the same moment, while event streams connect and disconnect, another
thread imports modules, Python's threads switch every 10 µs, and a process of our own keeps a
core busy. Fresh, because the run that imports the simulator's drivers, and with them Open3D,
is the first one of a process: Open3D's import walks ``sys.modules`` while other threads import,
and a run failed at its start with ``RuntimeError: dictionary changed size during iteration``
(about one trial in two before :func:`calstation.quiet.import_open3d`).

``CALSTATION_STRESS_TRIALS`` sets the number of trials (default 3).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("calstation_sim")

STARTS = Path(__file__).resolve().parents[1] / "support" / "stress_starts.py"
BURN = "while True: pass"


def test_web_stations_starting_runs_together_under_load_all_reach_their_first_prompt() -> None:
    trials = int(os.environ.get("CALSTATION_STRESS_TRIALS", "3"))
    burner = subprocess.Popen([sys.executable, "-c", BURN])
    failures = []
    try:
        for trial in range(trials):
            # the hang guard only catches a hang: it prints every thread's stack and ends
            proc = subprocess.run([sys.executable, str(STARTS), "4", "600"],
                                  capture_output=True, text=True)
            assert proc.returncode == 0, proc.stderr[-5000:]
            runs = json.loads(proc.stdout.strip().splitlines()[-1])["runs"]
            for run in runs:
                if run["started"] != 201 or not run["prompt"] or run["errors"]:
                    failures.append((trial, run))
    finally:
        burner.kill()
        burner.wait()
    assert not failures, json.dumps(failures, indent=1)  # each run's errors, whole
