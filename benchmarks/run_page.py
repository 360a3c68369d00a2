"""The run page and the run report of the default run: size and time.

Runs ``recipes/sim-periodicity.yaml`` unattended in a throw-away folder (or uses ``--db`` and
``--run`` of an existing station), serves the web station on 127.0.0.1 and prints:

1. the size of the run folder's ``report.html`` (and of plotly.js, written once beside the run
   folders);
2. the server's time for ``GET /runs/N`` and for its 3D views (``/runs/N/views.json``, which
   the report step kept in the run folder);
3. in Debian's chromium (when Playwright is there): the first contentful paint of ``/runs/N``
   and when every figure is drawn, with plotly.js cached as on any second visit.

Exit status 1 when ``report.html`` is over 1.5 MB or the page first paints after 1 s.

    .venv/bin/python benchmarks/run_page.py [--repeat 5] [--db URL --run N]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
import urllib.request
from pathlib import Path
from typing import Any

from qa_dashboard import CHROMIUM, serve

REPO = Path(__file__).resolve().parents[1]
REPORT_MAX = 1_500_000
PAINT_MAX_S = 1.0


def default_run(folder: Path) -> tuple[Any, int]:
    from calstation.cli._operator import ConsoleOperator
    from calstation.recipes import load_recipe
    from calstation.station.runs import start_run
    from calstation.storage.db import open_database

    db = open_database(f"sqlite:///{folder / 'station.db'}")
    run_id, _ = start_run(load_recipe(REPO / "recipes" / "sim-periodicity.yaml"), db,
                          ConsoleOperator(unattended=True), operator="bench",
                          data_dir=folder / "data")
    return db, run_id


def timed_get(url: str) -> tuple[float, int]:
    t = time.perf_counter()
    with urllib.request.urlopen(url, timeout=120) as r:
        n = len(r.read())
    return time.perf_counter() - t, n


def browser(url: str, repeat: int) -> list[tuple[float, float]] | None:
    """(first contentful paint, every figure drawn) in seconds, per visit."""
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        return None
    if not Path(CHROMIUM).exists():
        return None
    out = []
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox", "--disable-gpu"])
        page = b.new_page(viewport={"width": 1200, "height": 900})
        page.goto(url.rsplit("/runs/", 1)[0] + "/static/plotly.min.js")
        for _ in range(repeat):
            t = time.perf_counter()
            page.goto(url)
            page.wait_for_selector("body[data-report-ready]", timeout=120_000)
            ready = time.perf_counter() - t
            fcp = page.evaluate(
                "performance.getEntriesByName('first-contentful-paint')[0].startTime")
            out.append((float(fcp) / 1000.0, ready))
        b.close()
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--db", help="database URL of an existing station (with --run)")
    ap.add_argument("--run", type=int, help="run id in --db")
    args = ap.parse_args()

    from calstation.storage.db import Run, open_database
    from calstation.storage.report_html import plotly_file_name
    from calstation.web.app import create_app

    with tempfile.TemporaryDirectory(prefix="calstation-runpage-") as tmp:
        if args.db and args.run:
            db, run_id = open_database(args.db), args.run
        else:
            t = time.perf_counter()
            db, run_id = default_run(Path(tmp))
            print(f"default run {run_id} in {time.perf_counter() - t:.0f} s")
        with db.session("reading the run", read_only=True) as s:
            run = s.get(Run, run_id)
            assert run is not None, f"no run {run_id}"
            folder, status = Path(run.data_dir), run.status
        size = (folder / "report.html").stat().st_size
        beside = folder.parent / plotly_file_name()
        print(f"run {run_id} ({status}): report.html {size / 1e6:.2f} MB; plotly.js once "
              f"beside the run folders: {beside.stat().st_size / 1e6:.2f} MB")
        app = create_app(db, data_dir=Path(tmp), recipes_dir=Path(tmp) / "recipes")
        base, server = serve(app)
        page = [timed_get(f"{base}/runs/{run_id}") for _ in range(args.repeat)]
        print(f"GET /runs/{run_id}: median {statistics.median(t for t, _ in page):.3f} s, "
              f"{page[0][1] / 1e3:.0f} kB")
        first, n = timed_get(f"{base}/runs/{run_id}/views.json")
        again, _ = timed_get(f"{base}/runs/{run_id}/views.json")
        print(f"GET /runs/{run_id}/views.json (kept in the run folder by the report step): "
              f"{first:.3f} s, again {again:.3f} s, {n / 1e6:.2f} MB")
        visits = browser(f"{base}/runs/{run_id}", args.repeat)
        paint = statistics.median(t for t, _ in page)
        if visits:
            paint = statistics.median(f for f, _ in visits)
            print(f"/runs/{run_id} in chromium: first contentful paint median {paint:.3f} s, "
                  f"every figure drawn median {statistics.median(r for _, r in visits):.2f} s "
                  "(the 3D views in software WebGL: chromium runs without a GPU here)")
        server.should_exit = True
        db.dispose()
    ok = size <= REPORT_MAX and paint < PAINT_MAX_S
    print(f"report.html {size / 1e6:.2f} MB {'≤' if size <= REPORT_MAX else '>'} 1.5 MB; "
          f"first paint {paint:.3f} s {'<' if paint < PAINT_MAX_S else '≥'} {PAINT_MAX_S} s")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
