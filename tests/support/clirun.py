"""Run the ``calstation`` CLI: in-process, as the tests of its commands do, or as a process of
its own (:func:`cli_argv`, :func:`cli_env`) as a station's terminal does."""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any

import pytest

from calstation.cli import main


def run_cli(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    """``calstation argv…``: (exit code, stdout, stderr)."""
    code = 0
    try:
        main(argv)
    except SystemExit as exc:
        code = int(exc.code or 0)
    out, err = capsys.readouterr()
    return code, out, err


def cli_fails(capsys: pytest.CaptureFixture[str], out_dir: Path, *args: Any) -> str:
    """Run the CLI as the script does; it must exit 2 with one error line and leave nothing in
    ``out_dir``. Returns the error, its white space made single."""
    before = set(out_dir.iterdir())
    with pytest.raises(SystemExit) as exc:
        main([str(a) for a in args])
    assert exc.value.code == 2
    err = " ".join(capsys.readouterr().err.split())
    assert err.startswith("error: ") and "Traceback" not in err
    assert set(out_dir.iterdir()) == before, "a file was left behind"
    return err


def cli_env(tmp_path: Path) -> dict[str, str]:
    """The environment of a ``calstation`` process: none of the caller's ``CALSTATION_*``
    settings, its home in ``tmp_path/home``."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("CALSTATION_")}
    env["CALSTATION_HOME"] = str(tmp_path / "home")
    env["CALSTATION_OPERATOR"] = "e2e"
    env["COLUMNS"] = "120"
    return env


def cli_argv(*args: str) -> list[str]:
    """``calstation args…`` as a new Python process's command line."""
    return [sys.executable, "-c", "from calstation.cli import main; main()", *args]
