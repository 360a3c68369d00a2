"""A fleet's campaign: 1,000 stored runs over 4 stations re-processed with 1 and 2 local Dask
workers, on PostgreSQL.

Seeds a throw-away PostgreSQL server (Debian's binaries, as the tests use; or ``--db URL``) with
``--runs`` runs of the simulator's recordings (``--recordings`` simulated runs, shared by the runs
as a plant's runs never would: each run is still re-processed on its own), each stored as the
station stores it with its accepted H = today's + a seeded change: every ``--every``-th run
above the 0.5 mm tolerance in the work volume, the others within. Then ``calstation reprocess``
(the command itself, in a process of its own) with 1 and with 2 local workers, each a new
campaign, prints their throughput, checks that each flags exactly the seeded runs (in its
``--json`` and in the flagged-units table of its ``--report``), and that a sample of runs gives
results identical to ``calstation calibrate --run N``. Exits 1 when a check fails.

    python benchmarks/fleet_reprocess.py     # the full benchmark (about 45 min on two cores)
    python benchmarks/fleet_reprocess.py --runs 40 --limit 40 --sample 2   # a quick look
    python benchmarks/fleet_reprocess.py --workers 2   # the full scale, one campaign
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import subprocess
import sys
import tempfile
import time
from contextlib import ExitStack
from pathlib import Path

from calstation.storage.db import Calibration, CampaignRun, open_database
from calstation.testing.fleet import SeededRun, seed_runs, simulate_fleet
from calstation.testing.postgres import throwaway_postgres

STATIONS = ("line-1", "line-2", "line-3", "line-4")
TOLERANCE_MM = 0.5
ABOVE = ({"tx": 1.5e-3}, {"tz": 2e-3}, {"ry": math.radians(0.5)})
"""Changes seeded above the tolerance (each moves the work volume by 1 mm or more)."""
WITHIN = ({"tx": 0.2e-3}, {"rz": math.radians(-0.01)}, {})
"""Changes seeded within it."""


def _plan(n: int, recordings: int, every: int) -> tuple[list[SeededRun], set[str]]:
    runs, above = [], set()
    for k in range(n):
        serial = f"SN-{k + 1:05d}"
        if k % every == every - 1:
            change = ABOVE[(k // every) % len(ABOVE)]
            above.add(serial)
        else:
            change = WITHIN[k % len(WITHIN)]
        runs.append(SeededRun(STATIONS[k % len(STATIONS)], serial, k % recordings, dict(change)))
    return runs, above


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
    return subprocess.run([sys.executable, "-c", "from calstation.cli import main; main()",
                           *args], env=env, capture_output=True, text=True, timeout=6 * 3600)


def _campaign(url: str, workers: int, limit: int | None, report: Path) -> dict:
    args = ["reprocess", "--db", url, "--workers", str(workers), "--new", "--json",
            "--tolerance", str(TOLERANCE_MM), "--report", str(report)]
    if limit is not None:
        args += ["--limit", str(limit)]
    t0 = time.perf_counter()
    done = _cli(*args)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        raise SystemExit(f"reprocess --workers {workers} failed:\n{done.stderr[-3000:]}")
    try:
        data = json.loads(done.stdout)
    except ValueError:
        raise SystemExit(f"reprocess --workers {workers} printed no JSON "
                         f"({len(done.stdout)} characters):\n{done.stdout[-1000:]}\n"
                         f"{done.stderr[-3000:]}") from None
    data["wall_s"] = wall
    return data


def _flagged_in_report(html: str) -> set[str]:
    """The serials of the report's flagged-units table."""
    table = html.split('id="campaign-flagged"', 1)[1].split("</table>", 1)[0]
    return set(re.findall(r'<tr class="flagged"[^>]*><td class="text">([^<]+)</td>', table))


def _identical(url: str, run_ids: list[int], campaigns: list[int]) -> list[str]:
    """Differences between ``calibrate --run N`` and each campaign's result (none: identical)."""
    problems = []
    for run_id in run_ids:
        done = _cli("calibrate", "--run", str(run_id), "--db", url, "--json")
        if done.returncode not in (0, 3):
            problems.append(f"calibrate --run {run_id} failed: {done.stderr[-500:]}")
            continue
        single = json.loads(done.stdout)
        db = open_database(url)
        with db.session(read_only=True) as s:
            for campaign in campaigns:
                row = s.query(CampaignRun).filter_by(campaign_id=campaign, run_id=run_id).one()
                cal = s.get(Calibration, row.calibration_id)
                mine = s.get(Calibration, single["calibration_id"])
                assert cal is not None and mine is not None
                same = (cal.params() == mine.params() and cal.sigmas() == mine.sigmas()
                        and (cal.cost, cal.iterations) == (mine.cost, mine.iterations))
                if not same:
                    problems.append(f"run {run_id}: campaign {campaign} differs from "
                                    f"calibrate --run ({cal.params()} vs {mine.params()})")
        db.dispose()
    return problems


def _worker_counts(text: str) -> list[int]:
    try:
        counts = [int(w) for w in text.split(",")]
    except ValueError:
        counts = []
    if not counts or min(counts) < 1:
        raise SystemExit(f"--workers: expected worker counts like 1,2; got {text!r}")
    return counts


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=1000, help="runs to seed (default 1000)")
    ap.add_argument("--recordings", type=int, default=8, help="simulated runs they share")
    ap.add_argument("--every", type=int, default=10, help="every N-th run seeded above tolerance")
    ap.add_argument("--limit", type=int, default=None, help="re-process only the first N runs")
    ap.add_argument("--sample", type=int, default=5, help="runs checked against calibrate --run")
    ap.add_argument("--db", default=None, help="a PostgreSQL URL (default: a throw-away server)")
    ap.add_argument("--workers", default="1,2",
                    help="the campaigns' local worker counts, comma-separated (default 1,2)")
    args = ap.parse_args()
    counts = _worker_counts(args.workers)
    with ExitStack() as stack:
        url = args.db or stack.enter_context(throwaway_postgres())
        folder = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="fleet-bench-")))
        t0 = time.perf_counter()
        fleet = simulate_fleet(folder, seeds=list(range(1, args.recordings + 1)))
        print(f"simulated {args.recordings} runs and re-processed each once: "
              f"{time.perf_counter() - t0:.1f} s "
              f"({sum(r.refused != [] for r in fleet.today)} refused by today's engine)")
        plan, above = _plan(args.runs, args.recordings, args.every)
        db = open_database(url)
        t0 = time.perf_counter()
        ids = seed_runs(db, fleet.recipe, fleet.recordings, fleet.today, plan)
        db.dispose()
        print(f"seeded {len(ids)} runs over {len(STATIONS)} stations on {args.recordings} "
              f"recording sets into PostgreSQL: {time.perf_counter() - t0:.1f} s; "
              f"{len(above)} seeded above {TOLERANCE_MM} mm")
        n = min(args.limit or len(ids), len(ids))
        expected = {p.serial for p in plan[:n]} & above
        results, failed = {}, False
        for workers in counts:
            report = folder / f"campaign-{workers}.html"
            data = _campaign(url, workers, args.limit, report)
            results[workers] = data
            t = data["throughput"]
            flagged = {r["serial"] for r in data["runs"] if r["flagged"]}
            in_report = _flagged_in_report(report.read_text(encoding="utf-8"))
            failed |= flagged != expected or in_report != expected
            print(f"{workers} worker{'s' if workers > 1 else ''}: {t['runs']} runs in "
                  f"{t['seconds']:.1f} s ({data['wall_s']:.1f} s with start-up): "
                  f"{t['runs_per_minute']:.1f} runs/min; "
                  f"{data['totals']['reprocessed']} re-processed, {data['totals']['failed']} "
                  f"failed, {data['totals']['skipped']} skipped; flagged {len(flagged)} = the "
                  f"seeded ones: {flagged == expected}; the report's flagged units "
                  f"({len(in_report)}) = the seeded ones: {in_report == expected}")
        if {1, 2} <= set(counts):
            r1, r2 = (results[w]["throughput"]["runs_per_minute"] for w in (1, 2))
            print(f"speed-up with 2 workers: {r2 / r1:.2f}× (on {os.cpu_count()} cores)")
        step = max(1, n // max(1, args.sample))
        sample = ids[:n][::step][: args.sample]
        problems = _identical(url, sample, [results[w]["campaign"]["id"] for w in counts])
        print(f"calibrate --run N on runs {sample}: identical to every campaign: "
              f"{not problems}")
        for p in problems:
            print("  " + p)
        if problems or failed:
            sys.exit(1)


if __name__ == "__main__":
    main()
