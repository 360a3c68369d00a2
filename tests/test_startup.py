"""Start-up: the quick commands do not import the engine, the drivers' libraries or the database
they do not need (plugins register without importing them; docs/plugins.md, docs/performance.md)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
HEAVY = ("numpy", "scipy", "open3d", "can", "canopen", "serial", "sqlalchemy", "alembic")

PROBE = """
import json, sys
args, heavy = json.loads(sys.argv[1]), json.loads(sys.argv[2])
sys.argv = ["calstation", *args]
from calstation.cli import main
try:
    main()
except SystemExit:
    pass
print(json.dumps(sorted(m for m in sys.modules if m.split(".")[0] in heavy)))
"""


def _imported(args: list[str], tmp_path: Path) -> set[str]:
    env = {**os.environ, "CALSTATION_HOME": str(tmp_path / "home")}
    proc = subprocess.run(
        [sys.executable, "-c", PROBE, json.dumps(args), json.dumps(HEAVY)],
        capture_output=True, text=True, cwd=REPO, env=env, timeout=120,
    )
    last = proc.stdout.strip().splitlines()[-1]
    return {m.split(".")[0] for m in json.loads(last)}


@pytest.mark.parametrize(
    ("args", "allowed"),
    [
        (["--help"], set()),
        (["recipes", "validate", "recipes/sim-periodicity.yaml"], {"numpy"}),
        (["history"], {"sqlalchemy", "alembic"}),
    ],
    ids=["help", "recipes validate", "history"],
)
def test_quick_commands_leave_the_heavy_modules_alone(
    args: list[str], allowed: set[str], tmp_path: Path
) -> None:
    assert _imported(args, tmp_path) <= allowed
