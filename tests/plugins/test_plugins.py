"""The plugin manager: hooks documented, registries, duplicates, block and trace variables."""

from __future__ import annotations

import inspect
import json
import os
import re
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from calstation import hookimpl, plugins
from calstation.errors import PluginError
from calstation.plugins import hookspecs

DOCS = Path(__file__).resolve().parents[2] / "docs" / "plugins.md"


def _hook_names() -> list[str]:
    return [
        name
        for name, fn in inspect.getmembers(hookspecs, inspect.isfunction)
        if name.startswith("calstation_")
    ]


def test_hooks_are_documented() -> None:
    text = DOCS.read_text(encoding="utf-8")
    documented = set(re.findall(r"^### (calstation_\w+)$", text, flags=re.M))
    names = _hook_names()
    assert len(names) >= 7
    missing = sorted(set(names) - documented)
    assert not missing, f"hooks missing from docs/plugins.md: {missing}"
    stale = sorted(documented - set(names))
    assert not stale, f"docs/plugins.md documents hooks that do not exist: {stale}"


def test_every_hookspec_has_a_docstring_and_types() -> None:
    for name in _hook_names():
        fn = getattr(hookspecs, name)
        assert fn.__doc__ and len(fn.__doc__) > 40, name
        assert all(p.annotation is not inspect.Parameter.empty
                   for p in inspect.signature(fn).parameters.values()), name


class DriverPlugin:
    """Registers one driver of each kind and a strategy."""

    __name__ = "fake-drivers"

    @hookimpl
    def calstation_register_drivers(self, register: Any) -> None:
        for kind in ("lidar", "turntable", "encoder"):
            register(kind, "fake", lambda settings, context, k=kind: (k, settings))

    @hookimpl
    def calstation_register_cost_strategies(self, register: Any) -> None:
        register(SimpleNamespace(name="toy", fixture="spin_target"))


class Recorder:
    """Observes runs, remembering what it saw."""

    __name__ = "recorder"

    def __init__(self) -> None:
        self.events: list[tuple[Any, ...]] = []

    @hookimpl
    def calstation_step_finished(self, run: Any, step: str, status: str, result: Any) -> None:
        self.events.append(("step", run["id"], step, status, result))

    @hookimpl
    def calstation_run_finished(self, run: Any, status: str, summary: Any) -> None:
        self.events.append(("run", run["id"], status))

    @hookimpl
    def calstation_fixture_placed(self, context: Any, fixture: str, geometry: Any) -> None:
        self.events.append(("placed", fixture, geometry))


def test_registries_and_facade() -> None:
    recorder = Recorder()
    with plugins.isolated(DriverPlugin(), recorder, builtins=False):
        found = plugins.drivers()
        assert set(found) == {("lidar", "fake"), ("turntable", "fake"), ("encoder", "fake")}
        assert found[("lidar", "fake")].plugin == "fake-drivers"
        assert plugins.driver_factory("encoder", "fake")({"a": 1}, None) == ("encoder", {"a": 1})
        assert plugins.strategy("toy").fixture == "spin_target"
        with pytest.raises(PluginError, match="no lidar driver named 'nope'; installed: fake"):
            plugins.driver_factory("lidar", "nope")
        with pytest.raises(PluginError, match="installed: toy"):
            plugins.strategy("nope")
        plugins.fixture_placed(None, "qa_cube", {"edge": 0.1})
        plugins.step_finished({"id": 3}, "preflight", "passed", {"ok": True})
        plugins.run_finished({"id": 3}, "passed", {})
    assert recorder.events == [
        ("placed", "qa_cube", {"edge": 0.1}),
        ("step", 3, "preflight", "passed", {"ok": True}),
        ("run", 3, "passed"),
    ]


def test_isolation_restores_the_previous_manager() -> None:
    before = plugins.get_plugin_manager()
    with pytest.raises(RuntimeError), plugins.isolated(DriverPlugin(), builtins=False):
        assert ("lidar", "fake") in plugins.drivers()
        raise RuntimeError("boom")
    assert plugins.get_plugin_manager() is before


def test_duplicate_driver_is_an_error_naming_both_plugins() -> None:
    class Twin(DriverPlugin):
        __name__ = "twin"

    with plugins.isolated(DriverPlugin(), Twin(), builtins=False), pytest.raises(
        PluginError, match=r"registered twice: by .* and by"
    ):
        plugins.drivers()


def test_unknown_kind_and_unnamed_strategy_are_errors() -> None:
    class Bad:
        __name__ = "bad"

        @hookimpl
        def calstation_register_drivers(self, register: Any) -> None:
            register("laser", "x", lambda s, c: None)

        @hookimpl
        def calstation_register_cost_strategies(self, register: Any) -> None:
            register(object())

    with plugins.isolated(Bad(), builtins=False):
        with pytest.raises(PluginError, match="unknown kind 'laser'"):
            plugins.drivers()
        with pytest.raises(PluginError, match="without a name"):
            plugins.strategies()


def test_misspelled_hook_fails_loudly() -> None:
    class Typo:
        __name__ = "typo"

        @hookimpl
        def calstation_register_driver(self, register: Any) -> None:  # missing "s"
            pass

    with pytest.raises(PluginError, match="unknown hook"), plugins.isolated(
        Typo(), builtins=False
    ):
        pass


def test_builtins_register_through_the_hooks() -> None:
    with plugins.isolated(builtins=True):
        names = {i.name for i in plugins.plugin_report()}
    assert set(plugins.DEFAULT_PLUGINS) <= names


def _cli(*args: str, **env: str) -> subprocess.CompletedProcess[str]:
    full_env = {**os.environ, **env}
    return subprocess.run(
        [sys.executable, "-c", "from calstation.cli import main; main()", *args],
        capture_output=True, text=True, env=full_env, timeout=120,
    )


def test_block_variable_and_plugins_command() -> None:
    proc = _cli("plugins", "--json")
    assert proc.returncode == 0, proc.stderr
    listed = {p["name"]: p for p in json.loads(proc.stdout)["plugins"]}
    assert set(plugins.DEFAULT_PLUGINS) <= set(listed)
    blocked = plugins.DEFAULT_PLUGINS[-1]
    proc = _cli("plugins", "--json", CALSTATION_BLOCK_PLUGINS=f"{blocked}, example")
    assert proc.returncode == 0, proc.stderr
    names = {p["name"] for p in json.loads(proc.stdout)["plugins"]}
    assert blocked not in names and "example" not in names
    assert set(plugins.DEFAULT_PLUGINS[:-1]) <= names


def test_trace_variable_prints_hook_calls() -> None:
    proc = _cli("plugins", "--json", CALSTATION_TRACE_HOOKS="1")
    assert proc.returncode == 0, proc.stderr
    assert "[calstation hook] calstation_register_drivers(register) → " in proc.stderr
    assert "[calstation hook] calstation_register_commands(cli)" in proc.stderr


def test_a_settings_model_named_by_path_loads_when_a_recipe_is_checked() -> None:
    from calstation.errors import PluginError
    from calstation.plugins.recipe_checks import settings_model_of

    def factory(settings: object, context: object) -> None: ...

    factory.settings_model = "calstation_sim.settings:SimSettings"  # type: ignore[attr-defined]
    model = settings_model_of(factory)
    assert model.__name__ == "SimSettings" and model.model_validate({"seed": 3}).seed == 3
    factory.settings_model = "calstation_sim.settings:NoSuchModel"  # type: ignore[attr-defined]
    with pytest.raises(PluginError, match="NoSuchModel"):
        settings_model_of(factory)


def test_the_simulator_is_reached_through_its_hook_and_missing_it_says_how_to_install_it(
    tmp_path: Path,
) -> None:
    """calstation imports no simulator (import-linter's plugins-apart contract): the kit, the
    bench and plan find the one the calstation-sim plugin registers."""
    sim_plugin = pytest.importorskip("calstation_sim.plugin")
    with plugins.isolated(), pytest.raises(
        PluginError, match=r"no simulator named 'sim'.*calstation\[sim\]"
    ):
        plugins.simulator()
    with plugins.isolated(sim_plugin):
        simulator = plugins.simulator()
        assert simulator.name == "sim" and plugins.simulators() == {"sim": simulator}
        from calstation.plugins.simulation import Simulator
        from calstation.recipes import SHIPPED_DIR, load_recipe

        assert isinstance(simulator, Simulator)
        loaded = load_recipe(SHIPPED_DIR / "sim-periodicity.yaml")
        truth = simulator.truth(loaded, seed=3)
        assert truth == simulator.truth(loaded, seed=3) != simulator.truth(loaded, seed=4)

    class Twice:
        __name__ = "twice"

        @hookimpl
        def calstation_register_simulators(self, register: Any) -> None:
            register(SimpleNamespace(name="sim"))

    with plugins.isolated(sim_plugin, Twice()), pytest.raises(
        PluginError, match="simulator 'sim' registered twice"
    ):
        plugins.simulators()


def test_the_observer_payloads_carry_every_field_of_the_stored_run() -> None:
    """RunBrief and RunSummary (the TypedDicts the observer hooks declare) name exactly the
    keys storage gives a run, and the payloads built from them keep every value."""
    import datetime as dt

    from calstation.storage.db import Artifact, Run, Station, Step
    from calstation.storage.report import run_brief, run_summary

    t0 = dt.datetime(2026, 1, 2, 3, 4, 5, tzinfo=dt.UTC)
    run = Run(id=3, station=Station(name="st-1"), recipe_name="r", recipe_path=None,
              recipe_text="name: r", recipe_sha256="ab", operator="ann", unattended=True,
              data_dir="/runs/3", started_at=t0, finished_at=t0, status="passed", error="e",
              host="h", pid=1234, unit_serial="u", motor_stop={"ok": True})
    run.steps.append(Step(name="preflight", attempt=1, status="passed", started_at=t0,
                          result={"lines": 4}))
    run.artifacts.append(Artifact(kind="spin", path="/runs/3/spin.mcap", size_bytes=9,
                                  sha256="cd", status="complete"))
    brief, summary = run_brief(run), run_summary(run)

    def keys(typed: Any) -> set[str]:
        return set(typed.__required_keys__ | typed.__optional_keys__)

    assert set(brief) == keys(hookspecs.RunBrief)
    assert set(summary) == keys(hookspecs.RunSummary)
    assert set(summary["steps"][0]) == keys(hookspecs.StepRecord)
    assert set(summary["artifacts"][0]) == keys(hookspecs.ArtifactRecord)
    assert hookspecs.run_brief_payload(summary) == brief
    assert hookspecs.run_summary_payload(summary) == summary
