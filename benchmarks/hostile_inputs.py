"""Hostile inputs, measured: what each costs before calstation refuses it, and what it leaves.

Each case runs the real command in a process of its own, and reports its exit code, its first
line of error, its peak memory (the child's own maximum resident set, from ``wait4``), its wall
and CPU time, and whether the files it must not touch are as they were:

- decompression bombs through ``calstation reconstruct``: one zstd chunk and one lz4 chunk
  inflating to 2.5 GiB (declared), a zstd chunk declaring 1 MiB that inflates to 2.5 GiB, and
  forty 16 MiB chunks of zeros;
- recipes of 60,000 keys and of 20,000 unknown keys through ``calstation recipes validate``;
- two databases sharing one ``CALSTATION_HOME`` (the damaged-database advice): two simulated
  runs, the first run's files checked against the sha256 its database stored;
- a JSON export of ~40 kB onto a nearly full disk (a 64 KiB tmpfs; needs root and ``mount``, else
  skipped): the previous export checked.

``--compare REV`` runs the same cases on another revision side by side (its tree from ``git
archive``, the plugins of this checkout). Prints figures; not a test.

    .venv/bin/python benchmarks/hostile_inputs.py [--compare main] [--gib 2.5] [--skip-runs]
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import os
import subprocess
import sys
import tarfile
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
MiB = 1 << 20


@dataclass
class Outcome:
    """One case on one tree."""

    code: int
    said: str
    peak_mb: float
    wall_s: float
    cpu_s: float
    intact: str = ""


def _tree(rev: str, into: Path) -> Path:
    data = subprocess.run(["git", "archive", rev], cwd=REPO, check=True,
                          capture_output=True).stdout
    with tarfile.open(fileobj=io.BytesIO(data)) as tar:
        tar.extractall(into, filter="data")
    return into


def _env(tree: Path, **extra: str) -> dict[str, str]:
    plugins = sorted(str(p.parent) for p in (REPO / "plugins").glob("*/pyproject.toml"))
    return {**os.environ, "PYTHONPATH": os.pathsep.join([str(tree), *plugins]),
            "OMP_NUM_THREADS": "1", **extra}


MAIN = """
import atexit, os
def _peak():  # VmHWM: this program's own peak (ru_maxrss would keep the forking parent's)
    with open("/proc/self/status") as f, open(os.environ["CALSTATION_BENCH_PEAK"], "w") as o:
        o.write(next(ln for ln in f if ln.startswith("VmHWM:")).split()[1])
atexit.register(_peak)
from calstation.cli import main
main()
"""


def _run(tree: Path, argv: list[str], **env: str) -> Outcome:
    """``calstation argv`` from ``tree`` in a process of its own: its exit code and first error
    line, its peak memory (its own VmHWM), its wall time and CPU time (``wait4``)."""
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err, \
            tempfile.NamedTemporaryFile("r") as peak:
        t0 = time.perf_counter()
        # in the tree's folder: `python -c` puts the working folder first on sys.path
        proc = subprocess.Popen([sys.executable, "-c", MAIN, *argv], cwd=tree,
                                env=_env(tree, CALSTATION_BENCH_PEAK=peak.name, **env),
                                stdout=out, stderr=err, text=True)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        text = err.read().strip() or out.read().strip()
        peak_kb = float(peak.read() or "nan")
    lines = [ln for ln in text.splitlines() if ln.strip()]
    said = next((ln for ln in lines if ln.startswith("error")), lines[-1] if lines else "")
    return Outcome(proc.returncode, said[:160], peak_kb / 1024, wall,
                   usage.ru_utime + usage.ru_stime)


def _bombs(folder: Path, gib: float) -> dict[str, Path]:
    from calstation.testing.hostile import decompression_bomb

    size = int(gib * 1024 * MiB)
    return {
        f"zstd chunk of {gib:g} GiB": decompression_bomb(folder / "zstd.mcap", "zstd", size),
        f"lz4 chunk of {gib:g} GiB": decompression_bomb(folder / "lz4.mcap", "lz4", size),
        f"zstd chunk declaring 1 MiB, inflating to {gib:g} GiB": decompression_bomb(
            folder / "liar.mcap", "zstd", size, declared=MiB),
        "40 zstd chunks of 16 MiB": decompression_bomb(folder / "many.mcap", "zstd", 16 * MiB,
                                                        chunks=40),
    }


def _big_recipes(folder: Path) -> dict[str, Path]:
    """A 0.95 MB recipe of 60,000 keys and one of 20,000 unknown keys."""
    many = folder / "many-keys.yaml"
    many.write_text("\n".join(["name: big", "steps:",
                               *(f"  k{i:05d}: {i}" for i in range(60_000))]) + "\n")
    unknown = folder / "unknown-keys.yaml"
    unknown.write_text("\n".join(["name: big", *(f"k{i:05d}: {i}" for i in range(20_000))])
                       + "\n")
    return {"a recipe of 60,000 keys": many, "a recipe of 20,000 unknown keys": unknown}


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _two_databases(tree: Path, folder: Path) -> Outcome:
    """Two runs in one home, the first database moved aside in between: the first run's files
    as its database stored them?"""
    import sqlite3

    from calstation.testing import lean_recipe

    home = folder / "home"
    home.mkdir()
    recipe = lean_recipe(folder)
    env = {"CALSTATION_HOME": str(home), "CALSTATION_OPERATOR": "bench"}
    first = _run(tree, ["run", str(recipe), "--yes"], **env)
    with sqlite3.connect(home / "calstation.db") as conn:
        stored = conn.execute("SELECT path, sha256 FROM artifact WHERE run_id = 1").fetchall()
    for suffix in ("", "-wal", "-shm"):
        if (home / f"calstation.db{suffix}").exists():
            os.replace(home / f"calstation.db{suffix}", home / f"aside.db{suffix}")
    second = _run(tree, ["run", str(recipe), "--yes"], **env)
    changed = sum(1 for path, sha in stored if not Path(path).is_file() or _sha(Path(path)) != sha)
    second.intact = f"{len(stored) - changed} of {len(stored)} files of the first run intact"
    second.said = f"runs: exit {first.code}, then {second.code}"
    return second


def _full_disk(tree: Path, folder: Path) -> Outcome | None:
    """An export onto a 64 KiB tmpfs filled to its last page: the previous export?"""
    if os.geteuid() != 0:
        return None
    disk = folder / "disk"
    disk.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(disk)],
                      capture_output=True).returncode != 0:
        return None
    try:
        db = _seeded_database(tree, folder)
        out = disk / "calibration.json"
        out.write_text("the previous export\n")
        filler = disk / "filler"
        try:
            with filler.open("wb") as f:
                while True:
                    f.write(b"\0" * 512)
                    f.flush()
        except OSError:
            pass
        before = _sha(out)
        got = _run(tree, ["export", "1", "-f", "json", "--db", db, "-o", str(out)])
        got.intact = ("the previous export intact" if out.is_file() and _sha(out) == before
                      else _what_is_left(out))
        return got
    finally:
        subprocess.run(["umount", "-l", str(disk)], check=False)


SEED = """
import sys
from calstation.storage.db import Calibration, Run, Station, open_database
db = open_database(sys.argv[1])
with db.session() as s:
    run = Run(station=Station(name="bench"), recipe_name="r", recipe_text="x: 1",
              recipe_sha256="ab", operator="qa", data_dir=sys.argv[2], status="passed")
    s.add(run)
    s.flush()
    s.add(Calibration(run=run, stage="fine", strategy="periodicity", accepted=True,
                      diagnostics={"residuals_m": [1e-4 * k for k in range(1500)]},
                      **{p: 0.123456789 for p in ("tx", "ty", "tz", "rx", "ry", "rz")}))
db.dispose()
"""


def _what_is_left(out: Path) -> str:
    """What an export that replaced the previous one left: the whole new file, or a cut one."""
    try:
        json.loads(out.read_text())
    except (OSError, ValueError):
        return f"the previous export lost: {out.stat().st_size:,} bytes of cut JSON left"
    return "the new export written whole"


def _seeded_database(tree: Path, folder: Path) -> str:
    """A database with one run and its calibration (as `calstation history` shows runs; its
    diagnostics make the JSON export ~40 kB, pages more than the full disk's last one), made by
    ``tree``'s own code, so that each tree opens a database of its own revision."""
    url = f"sqlite:///{folder / 'qa.db'}"
    subprocess.run([sys.executable, "-c", SEED, url, str(folder)], cwd=tree, env=_env(tree),
                   check=True, capture_output=True)
    return url


def main() -> None:
    """Measure the cases and print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--compare", metavar="REV", help="also measure this git revision")
    ap.add_argument("--gib", type=float, default=2.5, help="the bombs' inflated size")
    ap.add_argument("--skip-runs", action="store_true", help="leave out the two-database runs")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="calstation-hostile-") as tmp:
        root = Path(tmp)
        trees = {"this checkout": REPO}
        if args.compare:
            trees[args.compare] = _tree(args.compare, root / "rev")
        bombs = _bombs(root, args.gib)
        calib = root / "calibration.json"
        calib.write_text(json.dumps({"H": dict.fromkeys(("tx", "ty", "tz", "rx", "ry", "rz"),
                                                        0.0)}))
        rows: list[tuple[str, str, Outcome | None]] = []
        for name, path in bombs.items():
            for label, tree in trees.items():
                got = _run(tree, ["reconstruct", str(path), "-c", str(calib), "-o",
                                       str(root / "out.ply")])
                got.intact = f"{path.stat().st_size / MiB:.2f} MB file"
                rows.append((name, label, got))
        for name, path in _big_recipes(root).items():
            for label, tree in trees.items():
                rows.append((name, label, _run(tree, ["recipes", "validate", str(path)])))
        for label, tree in trees.items():
            rows.append(("export onto a full disk", label,
                         _full_disk(tree, Path(tempfile.mkdtemp(dir=root)))))
            if not args.skip_runs:
                rows.append(("two databases in one home", label,
                             _two_databases(tree, Path(tempfile.mkdtemp(dir=root)))))
    print("| case | code | exit | peak memory | wall | CPU | files | said |")
    print("|---|---|---|---|---|---|---|---|")
    for name, label, got in rows:
        if got is None:
            print(f"| {name} | {label} | — | — | — | — | skipped (needs root and mount) | |")
            continue
        print(f"| {name} | {label} | {got.code} | {got.peak_mb:,.0f} MB | {got.wall_s:.1f} s | "
              f"{got.cpu_s:.1f} s | {got.intact} | {got.said.replace('|', '/')} |")


if __name__ == "__main__":
    main()
