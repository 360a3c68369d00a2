"""The paper's scenarios, its perturbation sets, and the simulated recordings behind them.

A scenario is one simulated station (paper Table I: range × pitch), simulated once with a fixed
seed; its three recordings (static, spin, cube) are reused by every method and start.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calstation.atomic import write_atomic
from calstation.bench import BenchError
from calstation.engine.frames import Extrinsics

SCENARIO_SEED_BASE = 1000
"""Scenario ``D<i>`` is simulated with seed ``SCENARIO_SEED_BASE + i``."""

PERTURBATION_SEED = 2026
"""Base seed of the perturbed starts; each (scenario, set) draws from its own stream."""


@dataclass(frozen=True)
class Scenario:
    """One paper dataset: the lidar ``range_m`` metres from the platter centre, pitched down by
    ``pitch_deg`` degrees, simulated with ``seed``."""

    name: str
    range_m: float
    pitch_deg: float
    seed: int

    @property
    def label(self) -> str:
        """E.g. ``"D5 (1.25 m, 45°)"``."""
        return f"{self.name} ({self.range_m:.2f} m, {self.pitch_deg:.0f}°)"


def paper_scenarios() -> list[Scenario]:
    """The nine scenarios D1–D9 of the paper's Table I (pitch rows 30/45/60°, range columns
    1.00/1.25/1.50 m), numbered as in the paper."""
    out: list[Scenario] = []
    i = 1
    for pitch in (30.0, 45.0, 60.0):
        for rng in (1.00, 1.25, 1.50):
            out.append(Scenario(f"D{i}", rng, pitch, SCENARIO_SEED_BASE + i))
            i += 1
    return out


def select_scenarios(names: list[str] | None) -> list[Scenario]:
    """The paper scenarios named in ``names`` (e.g. ``["D5", "D6"]``), all nine if ``None``."""
    every = paper_scenarios()
    if not names:
        return every
    by_name = {s.name.upper(): s for s in every}
    picked = []
    for name in names:
        key = name.strip().upper()
        if key not in by_name:
            raise BenchError(f"unknown scenario {name!r}; expected one of D1..D9")
        picked.append(by_name[key])
    return picked


@dataclass(frozen=True)
class PerturbationSet:
    """Uniform perturbations of the start: ±``translation_m`` on tx and tz, ±``rotation_deg`` on
    ry and rz; ty is fixed (as in the paper) and rx stays 0 (its gauge)."""

    name: str
    translation_m: float
    rotation_deg: float


PERTURBATION_SETS: dict[str, PerturbationSet] = {
    "A": PerturbationSet("A", 0.100, 1.0),
    "B": PerturbationSet("B", 0.200, 2.0),
}


def sample_starts(
    initial: Extrinsics, pset: PerturbationSet, n: int, scenario_index: int,
    seed: int = PERTURBATION_SEED,
) -> list[Extrinsics]:
    """``n`` starts: ``initial`` plus uniform perturbations of tx, tz (m) and ry, rz (rad).

    The stream depends only on (``seed``, ``scenario_index``, set name), so the same starts are
    used by every method, and the first k starts of a longer run equal those of a shorter one.
    """
    set_index = sorted(PERTURBATION_SETS).index(pset.name)
    rng = np.random.default_rng(np.random.SeedSequence([seed, scenario_index, set_index]))
    t, r = pset.translation_m, math.radians(pset.rotation_deg)
    starts = []
    for _ in range(n):
        d = rng.uniform(-1.0, 1.0, size=4)
        starts.append(
            Extrinsics(
                tx=initial.tx + t * d[0],
                ty=initial.ty,
                tz=initial.tz + t * d[1],
                rx=0.0,
                ry=initial.ry + r * d[2],
                rz=initial.rz + r * d[3],
            )
        )
    return starts


@dataclass(frozen=True)
class ScenarioData:
    """Where a simulated scenario's files are."""

    scenario: Scenario
    directory: Path
    static: Path
    spin: Path
    cube: Path
    truth: Path


STAMP = "scenario.json"


def _stamp(scenario: Scenario, recipe_sha256: str) -> dict[str, str | float]:
    return {
        "name": scenario.name,
        "range_m": scenario.range_m,
        "pitch_deg": scenario.pitch_deg,
        "seed": scenario.seed,
        "recipe_sha256": recipe_sha256,
    }


def scenario_data(scenario: Scenario, directory: Path) -> ScenarioData:
    """The file layout of a scenario simulated into ``directory``."""
    return ScenarioData(
        scenario,
        directory,
        directory / "static.mcap",
        directory / "spin.mcap",
        directory / "cube.mcap",
        directory / "truth.json",
    )


def is_simulated(scenario: Scenario, directory: Path, recipe_sha256: str) -> bool:
    """True if ``directory`` already holds this scenario simulated from this recipe (same seed)."""
    data = scenario_data(scenario, directory)
    stamp = directory / STAMP
    if not stamp.is_file() or not all(
        p.is_file() for p in (data.static, data.spin, data.cube, data.truth)
    ):
        return False
    try:
        return bool(json.loads(stamp.read_text()) == _stamp(scenario, recipe_sha256))
    except (OSError, ValueError):
        return False


def simulate_scenario(recipe_path: Path, scenario: Scenario, directory: Path) -> ScenarioData:
    """Simulate ``scenario`` into ``directory`` (static, spin and cube scans plus truth.json) with
    the recipe at ``recipe_path`` and the scenario's range, pitch and seed; reuse it if already
    there. A stamp file written last marks a complete simulation."""
    from calstation import plugins
    from calstation.recipes import load_recipe

    loaded = load_recipe(recipe_path)
    if is_simulated(scenario, directory, loaded.sha256):
        return scenario_data(scenario, directory)
    directory.mkdir(parents=True, exist_ok=True)
    (directory / STAMP).unlink(missing_ok=True)
    paths = plugins.simulator().simulate_run(
        loaded,
        directory,
        seed=scenario.seed,
        range_m=scenario.range_m,
        pitch_deg=scenario.pitch_deg,
        progress=False,
    )
    data = scenario_data(scenario, directory)
    for key, expected in (("static", data.static), ("spin", data.spin), ("cube", data.cube),
                          ("truth", data.truth)):
        got = Path(paths[key])
        if got.resolve() != expected.resolve():
            raise BenchError(f"simulate_run wrote {key} to {got}, expected {expected}")
    write_atomic(directory / STAMP, json.dumps(_stamp(scenario, loaded.sha256), indent=2), "stamp")
    return data


def load_truth(path: Path) -> Extrinsics:
    """The true H from a simulator ``truth.json`` (tx, ty, tz m; rx, ry, rz rad)."""
    try:
        d = json.loads(path.read_text())
        return Extrinsics(*(float(d[k]) for k in ("tx", "ty", "tz", "rx", "ry", "rz")))
    except (OSError, ValueError, KeyError) as exc:
        raise BenchError(f"{path}: not a usable truth.json ({exc})") from None
