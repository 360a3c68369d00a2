"""Start-up of the quick commands: ``calstation --help``, ``recipes validate`` and ``history``.

Prints figures; not a test. Each command runs as its own process, the way an operator or a
QA engineer runs it, and is timed from start to exit. ``history`` reads a database with the
rows of real runs: one simulated run of a lean recipe (a few seconds), copied to ``--runs``
runs over four stations. ``history --limit 1`` is its start-up (imports, the database opened
and recovered, one query, one row); plain ``history`` lists the newest 200 runs, the size of
table a station's database gives. The start-up target of each command is 0.3 s
(docs/performance.md, *Start-up*); the load average is printed at the start and end.
``--compare REV`` measures another git revision side by side (a temporary worktree, the same
database, runs alternated).

    .venv/bin/python benchmarks/startup.py [--runs 1000] [--repeat 9] [--compare REV]
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
TARGET_S = 0.3
CHILD_TABLES = ("step", "calibration", "cube_check", "artifact")


def _load() -> str:
    return "load average " + " ".join(f"{x:.2f}" for x in os.getloadavg())


def _copy_rows(url: str, runs: int) -> None:
    """Copy the database's one run, with its steps, calibrations, cube checks and artifacts, until
    it holds ``runs`` runs over four stations (ids remapped; everything else as stored)."""
    from sqlalchemy import select

    from calstation.storage.db import Base, Database

    tables = Base.metadata.tables
    db = Database(url)
    with db.engine.begin() as conn:
        (run,) = [dict(r._mapping) for r in conn.execute(select(tables["run"]))]
        children = {
            name: [dict(r._mapping) for r in conn.execute(select(tables[name]))]
            for name in CHILD_TABLES
        }
        stations = [run["station_id"]]
        stations += [_insert(conn, tables["station"], {"name": f"bench-{k}"}) for k in range(1, 4)]
        for k in range(1, runs):
            _copy_run(conn, tables, run, children, station_id=stations[k % 4])
    db.dispose()


def _insert(conn: Any, table: Any, values: dict[str, Any]) -> int:
    from sqlalchemy import insert

    return int(conn.execute(insert(table).values(**values)).inserted_primary_key[0])


def _copy_run(conn: Any, tables: Any, run: dict[str, Any],
              children: dict[str, list[dict[str, Any]]], station_id: int) -> None:
    row = {**run, "station_id": station_id}
    del row["id"]
    run_id = _insert(conn, tables["run"], row)
    new_ids: dict[str, dict[int, int]] = {}
    for name in CHILD_TABLES:
        new_ids[name] = {}
        for child in children[name]:
            values = {k: v for k, v in child.items() if k != "id"}
            values["run_id"] = run_id
            if values.get("step_id") is not None:
                values["step_id"] = new_ids["step"][values["step_id"]]
            if values.get("calibration_id") is not None:
                values["calibration_id"] = new_ids["calibration"][values["calibration_id"]]
            new_ids[name][child["id"]] = _insert(conn, tables[name], values)


def _launcher(root: Path) -> list[str]:
    """The ``calstation`` script of the checkout at ``root``, as its pyproject.toml declares it
    (what the installed script runs), started with this interpreter."""
    target = tomllib.loads((root / "pyproject.toml").read_text())["project"]["scripts"]
    module, func = target["calstation"].split(":")
    # that checkout's package and its own plugins (their import paths follow its layout)
    paths = [str(root), *sorted(str(p.parent) for p in root.glob("plugins/*/pyproject.toml"))]
    code = (f"import sys; sys.path[:0] = {paths!r}; from {module} import {func}; "
            f"sys.exit({func}())")
    return [sys.executable, "-c", code]


def _time(launcher: list[str], args: list[str], env: dict[str, str]) -> float:
    start = time.perf_counter()
    proc = subprocess.run([*launcher, *args], env=env, capture_output=True, text=True)
    elapsed = time.perf_counter() - start
    if proc.returncode != 0:
        sys.exit(f"calstation {' '.join(args)} failed:\n{proc.stdout[-2000:]}"
                 f"{proc.stderr[-2000:]}")
    return elapsed


def _worktree(rev: str) -> Path:
    tmp = Path(tempfile.mkdtemp(prefix="calstation-rev-"))
    subprocess.run(["git", "worktree", "add", "--detach", str(tmp), rev], cwd=REPO,
                   check=True, capture_output=True)
    return tmp


def _prepare(home: Path, runs: int) -> str:
    env = {**os.environ, "CALSTATION_HOME": str(home), "CALSTATION_OPERATOR": "bench"}
    url = f"sqlite:///{home / 'calstation.db'}"
    home.mkdir(parents=True)
    from calstation.testing import lean_recipe

    recipe = lean_recipe(home)
    print(f"one simulated run of {recipe.name} …", flush=True)
    proc = subprocess.run([*_launcher(REPO), "run", str(recipe), "--yes", "--db", url],
                          env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        sys.exit(f"the simulated run failed:\n{proc.stdout[-3000:]}{proc.stderr[-3000:]}")
    _copy_rows(url, runs)
    return url


def _commands(runs: int) -> dict[str, tuple[list[str], bool]]:
    """Label: (arguments, whether the start-up target applies)."""
    recipe = str(REPO / "recipes" / "sim-periodicity.yaml")
    return {
        "--help": (["--help"], True),
        "recipes validate": (["recipes", "validate", recipe], True),
        "history --limit 1 (start-up)": (["history", "--limit", "1"], True),
        f"history (newest {min(200, runs)} of {runs} runs)": (["history"], False),
    }


def main() -> None:
    """Run the benchmark and print the figures."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--runs", type=int, default=1000, help="runs in the database (default 1000)")
    ap.add_argument("--repeat", type=int, default=9, help="runs of each command (default 9)")
    ap.add_argument("--compare", metavar="REV", help="measure this git revision side by side")
    args = ap.parse_args()
    if args.runs < 1 or args.repeat < 1:
        ap.error("--runs and --repeat must be at least 1")
    print(f"calstation start-up; {os.cpu_count()} CPUs, {_load()}", flush=True)
    tmp = Path(tempfile.mkdtemp(prefix="calstation-startup-"))
    roots = {"this revision": REPO}
    try:
        if args.compare:
            roots[args.compare] = _worktree(args.compare)
        url = _prepare(tmp / "home", args.runs)
        env = {**os.environ, "CALSTATION_HOME": str(tmp / "home"), "CALSTATION_DB_URL": url}
        env.pop("PYTHONDONTWRITEBYTECODE", None)
        _measure(_commands(args.runs), {name: _launcher(root) for name, root in roots.items()},
                 env, args.repeat)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        for root in list(roots.values())[1:]:
            subprocess.run(["git", "worktree", "remove", "--force", str(root)], cwd=REPO,
                           capture_output=True)
    print(f"\nend: {_load()}")


def _measure(commands: dict[str, tuple[list[str], bool]], launchers: dict[str, list[str]],
             env: dict[str, str], repeat: int) -> None:
    """Each command under each revision, alternated so that load changes hit both: min and
    median, with the verdict against the target for this revision."""
    names = list(launchers)
    header = "".join(f" {name[:22]:>22}" for name in names)
    print(f"\ncalstation …{'':<31}{header}   (min / median, s; target {TARGET_S} s)")
    for label, (argv, has_target) in commands.items():
        times: dict[str, list[float]] = {name: [] for name in names}
        for name in names:
            _time(launchers[name], argv, env)  # bytecode caches written, files in the page cache
        for _ in range(repeat):
            for name in names:
                times[name].append(_time(launchers[name], argv, env))
        cells = "".join(f" {min(t):10.3f} / {statistics.median(t):7.3f}" for t in times.values())
        median = statistics.median(times[names[0]])
        verdict = ("ok" if median <= TARGET_S else "over the target") if has_target else "—"
        print(f"{label:<42}{cells}   {verdict}", flush=True)


if __name__ == "__main__":
    main()
