"""The shape sweep of docs/algorithms.md: whole simulated station runs with the shape strategy
(recipes/sim-shape.yaml), decided as the station decides them (the cube scan turning until the
accuracy budget holds), against the simulator's truth.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/shape_sweep.py [--noise 0.001] [--runs 24]
        [--jobs 2] [--out DIR]

It is ``ry_sweep.py station --recipe recipes/sim-shape.yaml``: the conditions cycle through line
rate (180, 1000 lines/s), background (on, off) and placement, the scenarios through the paper's
nine and 0.9 m / 40°; it prints how many runs were accepted, the accepted runs' axis offset and
direction errors, the turns taken, and the 3σ coverage of every parameter.
"""

from __future__ import annotations

import sys

import ry_sweep

if __name__ == "__main__":
    args = sys.argv[1:]
    if "--noise" not in args:
        args += ["--noise", "0.001"]
    if "--out" not in args:
        args += ["--out", str(ry_sweep.REPO / "out" / "shape-sweep")]
    sys.argv = [sys.argv[0], "station", "--recipe", str(ry_sweep.REPO / "recipes/sim-shape.yaml"),
                *args]
    ry_sweep.main()
