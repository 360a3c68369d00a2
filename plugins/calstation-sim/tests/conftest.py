"""Fixtures of the simulated station's tests: recipes derived from the default one."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest
import yaml

from calstation.recipes import LoadedRecipe, load_recipe

DEFAULT_RECIPE = Path(__file__).resolve().parents[3] / "recipes" / "sim-periodicity.yaml"

IDEAL = {
    "simulation.truth.tx_max": 0.0,
    "simulation.truth.tz_max": 0.0,
    "simulation.truth.ry_max_deg": 0.0,
    "simulation.truth.rz_max_deg": 0.0,
    "simulation.lidar.range_noise": 0.0,
    "simulation.lidar.dropout": 0.0,
    "simulation.lidar.mixed_pixel_prob": 0.0,
    "simulation.placement.position_sigma": 0.0,
    "simulation.placement.yaw_sigma_deg": 0.0,
    "simulation.turntable.speed_ripple": 0.0,
}
"""Overrides that make the station ideal: nominal pose, no noise, exact placement."""


@pytest.fixture
def make_recipe(tmp_path: Path) -> Callable[..., LoadedRecipe]:
    """``make_recipe({"simulation.lidar.dropout": 0.1, ...}, ideal=False)``: the default recipe
    with values replaced by dotted path, written to a file in ``tmp_path`` and loaded."""
    counter = [0]

    def make(overrides: dict[str, object] | None = None, *, ideal: bool = False) -> LoadedRecipe:
        data = yaml.safe_load(DEFAULT_RECIPE.read_text())
        for dotted, value in {**(IDEAL if ideal else {}), **(overrides or {})}.items():
            node = data
            *parents, leaf = dotted.split(".")
            for key in parents:
                node = node.setdefault(key, {})
            node[leaf] = value
        counter[0] += 1
        path = tmp_path / f"recipe-{counter[0]}.yaml"
        path.write_text(yaml.safe_dump(data))
        return load_recipe(path)

    return make
