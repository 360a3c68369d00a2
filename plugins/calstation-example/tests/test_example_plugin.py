"""The example plugin, registered into an isolated plugin manager (nothing else installed)."""

from __future__ import annotations

from pathlib import Path

import pytest
import typer
from calstation_example import plugin as example
from typer.testing import CliRunner

from calstation import plugins

RUN = {"id": 7, "station": "st-1", "recipe_name": "r", "operator": "ann"}


@pytest.fixture
def log(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    path = tmp_path / "events.jsonl"
    monkeypatch.setenv(example.ENV, str(path))
    return path


def test_observer_appends_one_line_per_event(log: Path) -> None:
    with plugins.isolated(example, builtins=False):
        plugins.run_started(RUN)
        plugins.step_finished(RUN, "static_scan", "passed", {"lines": 100})
        plugins.run_finished(
            RUN, "passed", {"calibrations": [{"stage": "fine", "accepted": True, "tx": 0.001}]}
        )
    events = example.read_events(log)
    assert [e["event"] for e in events] == ["run_started", "step_finished", "run_finished"]
    assert events[1]["step"] == "static_scan" and events[1]["result"] == {"lines": 100}
    assert events[2]["calibration"]["tx"] == 0.001
    assert all(e["run_id"] == 7 and e["station"] == "st-1" for e in events)


def test_observer_is_off_without_the_variable(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv(example.ENV, raising=False)
    monkeypatch.chdir(tmp_path)
    with plugins.isolated(example, builtins=False):
        plugins.step_finished(RUN, "preflight", "passed", {})
    assert list(tmp_path.iterdir()) == []


def test_plugin_reports_its_hooks() -> None:
    with plugins.isolated(example, builtins=False):
        (info,) = [i for i in plugins.plugin_report() if i.name == example.__name__]
    assert set(info.hooks) == {
        "calstation_register_drivers",
        "calstation_register_cost_strategies",
        "calstation_run_started",
        "calstation_step_finished",
        "calstation_run_finished",
        "calstation_register_commands",
    }


def test_command_prints_the_log(log: Path) -> None:
    with plugins.isolated(example, builtins=False):
        plugins.step_finished(RUN, "spin_scan", "failed", {"error": "no lines"})
        app = typer.Typer()

        @app.callback()
        def _root() -> None:
            """Root."""

        plugins.register_commands(app)
    result = CliRunner().invoke(app, ["example-log"])
    assert result.exit_code == 0, result.output
    assert "spin_scan" in result.output and "failed" in result.output
