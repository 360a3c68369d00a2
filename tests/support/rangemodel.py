"""Simulated stations whose lidar has systematic range errors (DESIGN §9), for the tests of the
range model and of the lidar's certificate."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

REPO = Path(__file__).resolve().parents[2]


def sensor_recipe(folder: Path, sensor: dict[str, Any], name: str) -> Path:
    """recipes/sim-periodicity.yaml with the simulated lidar's ``sensor`` errors, a certified
    cube (5 µm) of the platter's finish (the simulated platter and cube read alike unless
    ``sensor`` gives them reflectivities) and two cube turns, written to ``folder / name``."""
    data = yaml.safe_load((REPO / "recipes/sim-periodicity.yaml").read_text())
    data["simulation"]["sensor"] = sensor
    data["fixtures"]["qa_cube"].update(edge_tolerance=0.000005, same_finish_as_platter=True)
    data["steps"]["cube_scan"]["revolutions"] = 2.05
    path = folder / name
    path.write_text(yaml.safe_dump(data))
    return path


def run_scans(run: dict[str, Path]) -> Any:
    """The static, spin and cube scans of a simulated run, as the pipeline takes them."""
    from calstation.pipeline import Scans, turned
    from calstation.recordings.reader import read_recording

    return Scans(spin=turned(read_recording(run["spin"])),
                 static=read_recording(run["static"]),
                 cube=turned(read_recording(run["cube"])))
