"""Fixtures of the recordings tests."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.support.paths import DATA


@pytest.fixture(scope="module")
def spin(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A simulated run of the small v1 recipe (one fast turn of the spin target), once per test
    module: the bags of the import tests are written from its lines."""
    from calstation_sim import simulate_run

    from calstation.recipes import load_recipe

    out = tmp_path_factory.mktemp("sim")
    return simulate_run(load_recipe(DATA / "v1" / "recipe.yaml"), out, progress=False)
