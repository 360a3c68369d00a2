"""Start-up: the quick commands do not import the engine, the drivers' libraries or the database
they do not need (plugins register without importing them; docs/plugins.md, docs/performance.md)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
HEAVY = (
    "numpy", "scipy", "open3d", "can", "canopen", "serial", "sqlalchemy", "alembic", "pydantic",
)

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
        (["recipes", "validate", "recipes/sim-periodicity.yaml"], {"pydantic"}),
        (["history"], {"sqlalchemy", "alembic", "pydantic"}),
    ],
    ids=["help", "recipes validate", "history"],
)
def test_quick_commands_leave_the_heavy_modules_alone(
    args: list[str], allowed: set[str], tmp_path: Path
) -> None:
    assert _imported(args, tmp_path) <= allowed


def test_version_is_the_installed_distributions(tmp_path: Path) -> None:
    """``calstation --version`` and ``calstation version`` print the version the package was
    built with (from its git tag: setuptools-scm), quickly. The version expected is the one
    installed in the environment's site-packages: a checkout's own ``calstation.egg-info`` (on
    this process's path, rewritten by any later build) may tell another."""
    import sysconfig
    from importlib.metadata import distributions

    site = [sysconfig.get_paths()["purelib"]]
    installed = {d.version for d in distributions(name="calstation", path=site)}
    assert len(installed) == 1, installed
    for args in (["--version"], ["version"]):
        proc = subprocess.run([sys.executable, "-m", "calstation", *args], capture_output=True,
                              text=True, cwd=tmp_path, timeout=120)
        assert proc.returncode == 0, proc.stderr
        assert proc.stdout.strip() == f"calstation {min(installed)}"
    assert _imported(["--version"], tmp_path) == set()


def test_a_database_at_the_newest_revision_opens_without_alembic(tmp_path: Path) -> None:
    """The command that makes a new database creates its tables with Alembic; the next ones
    find it at the newest revision from the version table alone."""
    assert "alembic" in _imported(["db", "upgrade"], tmp_path)
    assert _imported(["history"], tmp_path) <= {"sqlalchemy", "pydantic"}


def test_a_run_preloads_the_engine_in_the_background() -> None:
    """The station imports the engine on a thread of its own when a run starts, so that the
    steps after the scans do not wait for the imports; Open3D first, before that thread starts
    and before the drivers open (its import fails when another thread imports meanwhile)."""
    probe = (
        "import sys, json\n"
        "import calstation.station.runs\n"
        "from calstation.station.preload import preload_engine, ENGINE_MODULES\n"
        "before = [m for m in (*ENGINE_MODULES, 'open3d') if m in sys.modules]\n"
        "thread = preload_engine()\n"
        "open3d_first = 'open3d' in sys.modules\n"
        "thread.join()\n"
        "print(json.dumps([before, open3d_first,\n"
        "                  [m for m in ENGINE_MODULES if m in sys.modules]]))\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, cwd=REPO, timeout=120
    )
    before, open3d_first, after = json.loads(proc.stdout.strip().splitlines()[-1])
    assert "open3d" not in before and "calstation.engine.shape" not in before
    assert open3d_first
    assert after == [
        "calstation.engine.periodicity",
        "calstation.engine.shape",
        "calstation.engine.cube",
        "calstation.engine.joint",
        "calstation.engine.fusion",
    ]


GC_PROBE = """
import gc, json, sys
import calstation.storage.db
seen = []

def spy(self, *args, **kwargs):
    seen.append(gc.isenabled())
    raise SystemExit(0)

calstation.storage.db.Database.__init__ = spy
from calstation.cli import main
try:
    main(json.loads(sys.argv[1]))
except SystemExit:
    pass
print(json.dumps([seen, gc.isenabled()]))
"""


@pytest.mark.parametrize(
    ("args", "collector_on"),
    [
        (["history"], False),
        (["show", "1"], False),
        (["db", "info"], True),
        (["calibrate", "--run", "1"], True),
    ],
    ids=["history", "show", "db info", "calibrate"],
)
def test_only_the_quick_commands_run_without_the_cyclic_collector(
    args: list[str], collector_on: bool, tmp_path: Path
) -> None:
    """The quick commands leave Python's cyclic garbage collector off while they open the
    database; every other command has it on by then. Called in-process, ``main`` leaves it as it
    found it."""
    env = {**os.environ, "CALSTATION_HOME": str(tmp_path / "home")}
    proc = subprocess.run(
        [sys.executable, "-c", GC_PROBE, json.dumps(args)],
        capture_output=True, text=True, cwd=REPO, env=env, timeout=120,
    )
    seen, after = json.loads(proc.stdout.strip().splitlines()[-1])
    assert seen == [collector_on], proc.stderr[-2000:]
    assert after is True
