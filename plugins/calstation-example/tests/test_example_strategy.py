"""The example strategy on simulated scans from the kit (calstation.testing.fixtures)."""

from __future__ import annotations

from pathlib import Path

import pytest
from calstation_example import plugin as example
from calstation_example.strategy import RyHeldStrategy

from calstation import plugins
from calstation.engine.metrics import axis_errors
from calstation.errors import RecipeError
from calstation.plugins.cost_strategies import run_strategy
from calstation.plugins.recipe_checks import check_plugins
from calstation.recipes import load_recipe
from calstation.recordings.reader import read_recording
from calstation.testing import SimulatedScans


def test_strategy_refines_with_ry_held(simulated_scans: SimulatedScans, strategy_start) -> None:
    strategy = RyHeldStrategy()
    recording = read_recording(simulated_scans.scan_of(strategy.fixture))
    result, warnings = run_strategy(strategy, recording, strategy_start,
                                    simulated_scans.recipe.recipe)
    assert warnings == []
    assert result.strategy == "example-ry-held" and result.timings["total"] > 0
    assert result.H.ry == strategy_start.ry  # held
    before = axis_errors(strategy_start, simulated_scans.truth)["axis_offset_m"]
    after = axis_errors(result.H, simulated_scans.truth)["axis_offset_m"]
    assert after < 3e-3 and after < before


BASE = (Path(__file__).resolve().parents[3] / "recipes" / "sim-periodicity.yaml").read_text()


@pytest.mark.parametrize(
    "options,field,marker",
    [
        ("    example-ry-held:\n      bogus: 1\n", "calibration.options.example-ry-held.bogus",
         "bogus:"),
        ("    example-ry-held:\n      box: round\n", "calibration.options.example-ry-held.box",
         "box:"),
    ],
)
def test_recipe_options_are_checked_with_line(
    tmp_path: Path, options: str, field: str, marker: str
) -> None:
    text = BASE.replace("calibration:\n", "calibration:\n  options:\n" + options, 1)
    assert text != BASE
    path = tmp_path / "r.yaml"
    path.write_text(text, encoding="utf-8")
    with plugins.isolated(example), pytest.raises(RecipeError) as info:
        check_plugins(load_recipe(path))
    line = text[: text.index(marker)].count("\n") + 1
    assert f"{path}:{line}: {field}: " in str(info.value), str(info.value)
