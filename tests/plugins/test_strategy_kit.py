"""What calstation checks around a strategy: its options model, its result, its timing; and the
``plugins`` listing of strategies with their plugin."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from typing import Any

import pytest
from pydantic import BaseModel, ConfigDict

from calstation import hookimpl, plugins
from calstation.engine.frames import Extrinsics
from calstation.engine.result import CalibrationResult
from calstation.errors import FineTuningError, PluginError, RecipeError
from calstation.plugins.cost_strategies import check_result, recipe_option_problems, run_strategy
from calstation.recipes import parse_recipe

START = Extrinsics(tx=0.01, ty=1.0, tz=0.002, rx=0.0, ry=0.001, rz=-0.78)


class Returns:
    """A strategy returning ``H`` (or ``value`` itself when it is no H)."""

    name = "returns"
    fixture = "spin_target"

    def __init__(self, value: Any, timings: dict[str, float] | None = None) -> None:
        self.value = value
        self.timings = timings or {}

    def run(self, recording: Any, start: Any, recipe: Any, progress: Any = None) -> Any:
        if not isinstance(self.value, Extrinsics):
            return self.value
        return CalibrationResult(self.value, {}, 0.5, 3, self.name, timings=self.timings)


def test_an_implausible_result_is_an_error_naming_the_parameter() -> None:
    far = START.with_(ry=math.radians(90.0), tx=0.76)
    with pytest.raises(FineTuningError) as info:
        run_strategy(Returns(far), None, START, None)  # type: ignore[arg-type]
    message = str(info.value)
    assert "strategy 'returns' returned tx = 760.00 mm" in message
    assert "750.00 mm from its start 10.00 mm" in message and "300.00 mm" in message
    with pytest.raises(FineTuningError, match="not a CalibrationResult"):
        check_result(Returns(None), {"tx": 1.0}, START)


def test_a_plausible_result_is_timed_and_odd_details_are_warnings() -> None:
    near = START.with_(tx=START.tx + 0.150, rz=START.rz + math.radians(1.5))
    result, warnings = run_strategy(Returns(near), None, START, None)  # type: ignore[arg-type]
    assert near == result.H and warnings == []
    assert math.isfinite(result.timings["total"]) and result.timings["total"] >= 0
    # its own finite timing is kept
    result, _ = run_strategy(Returns(near, {"total": 12.5}), None, START, None)  # type: ignore[arg-type]
    assert result.timings["total"] == 12.5
    moved = CalibrationResult(near.with_(rx=0.01), {}, math.nan, 1, "other")
    _, warnings = check_result(Returns(near), moved, START)
    assert any("moved rx" in w for w in warnings)
    assert any("cost of nan" in w for w in warnings)
    assert any("labelled its result 'other'" in w for w in warnings)


class Opts(BaseModel):
    model_config = ConfigDict(extra="forbid")
    radius: float = 0.1
    mode: str = "fast"


class WithOptions:
    name = "with-options"
    fixture = "qa_cube"
    options_model = Opts

    def run(self, *args: Any) -> Any:
        raise AssertionError("not run here")


class StrategyPlugin:
    __name__ = "strategy-plugin"

    def __init__(self, *strategies: Any) -> None:
        self.strategies = strategies

    @hookimpl
    def calstation_register_cost_strategies(self, register: Any) -> None:
        for s in self.strategies:
            register(s)


RECIPE = """name: r
station:
  id: st
  lidar: {driver: a}
  turntable: {driver: b}
  encoder: {driver: c}
calibration:
  strategy: with-options
  options:
    with-options:
      radius: wide
      bogus: 1
"""


def test_options_model_problems_name_the_option() -> None:
    recipe = parse_recipe(RECIPE)
    with plugins.isolated(StrategyPlugin(WithOptions()), builtins=False):
        problems = recipe_option_problems(recipe, plugins.strategies())
    assert (("calibration", "options", "with-options", "bogus"), "unknown option") in problems
    assert any(loc[-1] == "radius" and "number" in msg for loc, msg in problems)
    # the built-in periodicity strategy takes no options at all, checked even without plugins
    with pytest.raises(RecipeError, match=r"calibration\.options\.periodicity\.bogus"):
        parse_recipe(RECIPE.replace("with-options:\n      radius: wide\n      bogus: 1",
                                    "periodicity:\n      bogus: 1"))


def test_a_bad_options_model_is_refused_at_registration() -> None:
    class Bad:
        name = "bad"
        fixture = "qa_cube"
        options_model = "radius: float"

    with plugins.isolated(StrategyPlugin(Bad()), builtins=False), pytest.raises(
        PluginError, match="strategy-plugin: strategy 'bad': options_model must be a pydantic"
    ):
        plugins.strategies()


def test_plugins_command_lists_each_strategy_with_its_plugin() -> None:
    proc = subprocess.run(
        [sys.executable, "-c", "from calstation.cli import main; main()", "plugins", "--json"],
        capture_output=True, text=True, env=dict(os.environ), timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    rows = {s["name"]: s for s in json.loads(proc.stdout)["strategies"]}
    assert rows["shape"]["plugin"] == "calstation.plugins.builtin.strategies"
    assert rows["shape"]["options"] == ["box", "estimate_ry", "coarse", "known_size"]
    assert rows["periodicity"]["options"] == []  # its settings are calibration.periodicity
    if "example-ry-held" in rows:  # the example plugin, when installed
        assert rows["example-ry-held"]["plugin"] == "example"


CONFORMANCE = """
from calstation import plugins
from calstation.clock import HostClock
from calstation.drivers import DriverContext
from calstation.testing.conformance import check_encoder, check_lidar, check_turntable

names = sorted(p.name for p in plugins.plugin_report())
assert names == ["example"], names
ctx = DriverContext(clock=HostClock())
make = lambda kind: lambda: plugins.driver_factory(kind, "example")({}, ctx)
print(len(check_lidar(make("lidar")).passed), len(check_turntable(make("turntable"),
      spin_s=1.0).passed), len(check_encoder(make("encoder")).passed))
"""


def test_example_driver_passes_the_kit_with_no_other_plugin() -> None:
    """A fresh process where every plugin but the example one is blocked: the kit alone, through
    the ordinary entry-point loading, accepts the example drivers."""
    pytest.importorskip("calstation_example")
    others = ",".join([*plugins.DEFAULT_PLUGINS, "sim", "hokuyo", "canopen"])
    proc = subprocess.run(
        [sys.executable, "-c", CONFORMANCE], capture_output=True, text=True, timeout=120,
        env={**os.environ, "CALSTATION_BLOCK_PLUGINS": others},
    )
    assert proc.returncode == 0, proc.stderr
    lidar, turntable, encoder = (int(n) for n in proc.stdout.split())
    assert lidar >= 15 and turntable >= 8 and encoder >= 6
