"""The terminal's prompts through a real terminal (a pty, pexpect): only a listed answer moves the
run on. A placement prompt answered with anything but ``continue`` leaves the turntable at rest
and asks again."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

from calstation.storage.db import Step, open_database

pexpect = pytest.importorskip("pexpect")

REPO = Path(__file__).resolve().parents[2]
PROMPT = r"Type continue \(c\) when it is placed"


def _spawn(home: Path, *args: str) -> pexpect.spawn:
    env = {**os.environ, "CALSTATION_HOME": str(home), "COLUMNS": "120", "TERM": "dumb",
           "CALSTATION_OPERATOR": "pty"}
    env.pop("CALSTATION_DB_URL", None)
    return pexpect.spawn(sys.executable, ["-m", "calstation", *args], cwd=str(REPO), env=env,
                         encoding="utf-8", timeout=180, dimensions=(40, 120))


def _spin_recordings(home: Path) -> list[Path]:
    """Spin recordings anywhere under ``home`` (the run folder is ``runs/<database>/<run>``)."""
    return sorted(home.rglob("spin*.mcap"))


def _steps(home: Path) -> list[tuple[str, str]]:
    db = open_database(f"sqlite:///{home / 'calstation.db'}")
    try:
        with db.session() as s:
            return [(st.name, st.status) for st in s.query(Step).order_by(Step.id)]
    finally:
        db.dispose()


def test_a_placement_prompt_moves_nothing_until_continue(tmp_path: Path) -> None:
    # the targetless recipe has no L-target: the first prompt places the spin target, and the
    # next step spins the turntable
    child = _spawn(tmp_path, "run", "recipes/sim-targetless.yaml")
    try:
        child.expect("Place the spin target on the platter, its centre 60 mm from the axis")
        child.expect(PROMPT)
        for answer in ("x", "n", "exit", "stop", ""):
            child.sendline(answer)
            child.expect("is not an answer here")
            child.expect(PROMPT)  # asked again
        assert _spin_recordings(tmp_path) == []
        child.sendline("abort")
        # the run's report, even of an aborted run, and where it is
        child.expect("no calibration was stored in this run")
        child.expect(r"report: \S*runs/\S+/1/report\.html")
        child.expect(pexpect.EOF)
    finally:
        child.close(force=True)
    assert child.exitstatus == 3  # aborted
    steps = _steps(tmp_path)
    assert ("place_spin_target", "aborted") in steps
    assert all(name != "spin_scan" for name, _ in steps), steps  # the turntable never spun
    assert _spin_recordings(tmp_path) == []


def test_end_of_input_at_a_prompt_aborts(tmp_path: Path) -> None:
    child = _spawn(tmp_path, "run", "recipes/sim-targetless.yaml")
    try:
        child.expect(PROMPT)
        child.sendeof()
        child.expect(pexpect.EOF)
    finally:
        child.close(force=True)
    assert child.exitstatus == 3
    assert all(name != "spin_scan" for name, _ in _steps(tmp_path))


def test_a_steps_progress_bar_counts_its_time_through_all_its_phases() -> None:
    """A step's phase that reaches 100 % (the platter up to speed) is not the step's end: the
    bar's clock goes on through the next phase (the scan) instead of showing 0:00:00."""
    import io

    from rich.console import Console

    from calstation.cli._operator import ConsoleOperator

    now = [1000.0]
    out = io.StringIO()
    console = Console(file=out, force_terminal=True, width=100, get_time=lambda: now[0])
    with ConsoleOperator(console=console).progress("spin scan") as update:
        update("waiting for speed", 1.0)
        now[0] += 65.0
        update("scanning", 0.5)
        now[0] += 10.0
    assert "0:01:15" in out.getvalue(), out.getvalue()[-300:]
