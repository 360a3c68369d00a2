"""Every snippet of docs/plugins.md runs as shown: the blocks headed ``# FILE`` are written into
their files (``# FILE, continued`` adds to one), the test files among them are run as pytest
would (fixtures by name), any other Python block runs on its own, the TOML parses, and the shell
commands succeed."""

from __future__ import annotations

import importlib.util
import inspect
import os
import re
import shlex
import subprocess
import sys
import tomllib
from pathlib import Path
from typing import Any

import pytest
from typer.testing import CliRunner

from calstation.testing.fixtures import simulated_scans, strategy_start  # noqa: F401

DOC = Path(__file__).resolve().parents[2] / "docs" / "plugins.md"
BLOCK = re.compile(r"^```(\w+)\n(.*?)^```", re.MULTILINE | re.DOTALL)
HEADER = re.compile(r"^# ([\w./-]+\.(?:py|toml))(, continued)?\s*$")


def snippets() -> list[tuple[str, str]]:
    """(language, code) of every fenced block of docs/plugins.md, in order."""
    return BLOCK.findall(DOC.read_text(encoding="utf-8"))


def _files(blocks: list[tuple[str, str]]) -> tuple[dict[str, str], list[str]]:
    files: dict[str, str] = {}
    loose: list[str] = []
    for lang, code in blocks:
        if lang != "python":
            continue
        m = HEADER.match(code.splitlines()[0])
        if m is None:
            loose.append(code)
        elif m.group(2):
            assert m.group(1) in files, f"{m.group(1)} continued before it starts"
            files[m.group(1)] += "\n\n" + code
        else:
            assert m.group(1) not in files, f"{m.group(1)} starts twice"
            files[m.group(1)] = code
    return files, loose


def _run_tests(module: Any, fixtures: dict[str, Any]) -> list[str]:
    """Call the module's ``test_*`` functions and ``Test*`` classes' ``test_*`` methods as pytest
    would, with fixtures by parameter name; returns what ran."""
    ran = []

    def call(fn: Any, name: str) -> None:
        kwargs = {p: fixtures[p] for p in inspect.signature(fn).parameters}
        try:
            fn(**kwargs)
            ran.append(name)
        except pytest.skip.Exception:
            ran.append(f"{name} (skipped)")

    for name, obj in vars(module).items():
        if name.startswith("test_") and inspect.isfunction(obj):
            call(obj, name)
        elif name.startswith("Test") and inspect.isclass(obj):
            for method in sorted(m for m in dir(obj) if m.startswith("test_")):
                instance = obj()
                if hasattr(instance, "setup_method"):
                    instance.setup_method()
                call(getattr(instance, method), f"{name}.{method}")
    return ran


def test_every_snippet_runs(tmp_path: Path, simulated_scans: Any, strategy_start: Any,  # noqa: F811
                            monkeypatch: pytest.MonkeyPatch) -> None:
    blocks = snippets()
    assert len(blocks) >= 10
    files, loose = _files(blocks)
    assert {"my_package/plugin.py", "my_package/driver.py", "my_package/strategy.py",
            "tests/test_my_drivers.py", "tests/test_my_strategy.py"} <= set(files)
    for name, code in files.items():
        path = tmp_path / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(code + "\n", encoding="utf-8")
    monkeypatch.syspath_prepend(str(tmp_path))
    for name in [m for m in sys.modules if m == "my_package" or m.startswith("my_package.")]:
        monkeypatch.delitem(sys.modules, name)
    # pyproject.toml: the entry point names the plugin module shown
    (toml,) = [code for lang, code in blocks if lang == "toml"]
    project = tomllib.loads(toml)["project"]
    assert project["entry-points"]["calstation"] == {"myplugin": "my_package.plugin"}
    # the test files, run as pytest would
    fixtures = {"simulated_scans": simulated_scans, "strategy_start": strategy_start,
                "tmp_path": tmp_path}
    ran: list[str] = []
    for name in sorted(files):
        if not name.startswith("tests/"):
            continue
        spec = importlib.util.spec_from_file_location(f"plugin_docs_{Path(name).stem}",
                                                      tmp_path / name)
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        ran += _run_tests(module, fixtures)
    assert {"test_my_observer", "TestMyDrivers.test_lidar_conforms", "test_my_lidar_alone",
            "test_version_query", "test_mine"} <= set(ran), ran
    for code in loose:
        exec(compile(code, str(DOC), "exec"), {"__name__": "plugin_docs_snippet"})
    # the shell commands
    from calstation.cli import _build, app

    _build()
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), *sys.path])}
    for lang, code in blocks:
        if lang != "sh":
            continue
        for line in code.splitlines():
            words = shlex.split(line, comments=True)
            if not words:
                continue
            if words[0] == "calstation":
                res = CliRunner().invoke(app, words[1:])
                assert res.exit_code == 0, (line, res.output)
            else:
                assert words[0] == "python", line
                proc = subprocess.run([sys.executable, *words[1:]], env=env, cwd=tmp_path,
                                      capture_output=True, text=True, timeout=60)
                assert proc.returncode == 0, (line, proc.stderr)
