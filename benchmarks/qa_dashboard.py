"""The QA dashboard over a fleet's history: load time, and which points its control charts flag.

Seeds a throw-away SQLite database with ``--stations`` stations × ``--weeks`` weeks ×
``--per-day`` runs a day (``calstation.testing.qa_history``: the simulator's stations, their
calibration scatter, realistic failures and repeated steps), with a drift of tz on the third
station from day ``--drift-day`` on. Serves the web station on 127.0.0.1 and prints:

1. the server's time to answer ``GET /dashboard`` (median of ``--repeat``) and its size;
2. when Debian's chromium and Playwright are there, the page's load in the browser: from the
   request until every figure is drawn (median of ``--repeat``);
3. per station and parameter, the points out of control; for the drifting station, how many of
   the drifting runs are flagged and the first one (days after the drift began).

Exit status 1 when the dashboard takes longer than ``--budget`` seconds or the drift is not
flagged.

    .venv/bin/python benchmarks/qa_dashboard.py [--stations 4] [--weeks 8] [--per-day 40]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path
from typing import Any

CHROMIUM = "/usr/bin/chromium"


def serve(app: Any) -> tuple[str, Any]:
    """``app`` served by uvicorn in a thread on a free local port: (base URL, server)."""
    import socket

    import uvicorn

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = int(s.getsockname()[1])
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port,
                                           log_level="warning", server_header=False))
    threading.Thread(target=server.run, daemon=True).start()
    deadline = time.monotonic() + 20
    while not server.started and time.monotonic() < deadline:
        time.sleep(0.05)
    return f"http://127.0.0.1:{port}", server


def server_times(url: str, repeat: int) -> tuple[list[float], int]:
    times, size = [], 0
    for _ in range(repeat):
        t = time.perf_counter()
        with urllib.request.urlopen(url, timeout=60) as r:
            size = len(r.read())
        times.append(time.perf_counter() - t)
    return times, size


def browser_times(url: str, repeat: int) -> list[float] | None:
    """Seconds from the request until every figure is drawn, in headless chromium."""
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        return None
    if not Path(CHROMIUM).exists():
        return None
    out = []
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM,
                                    args=["--no-sandbox", "--disable-gpu"])
        page = browser.new_page(viewport={"width": 1300, "height": 900})
        page.goto(url.replace("/dashboard", "/static/plotly.min.js"))  # cached, as every day
        for _ in range(repeat):
            t = time.perf_counter()
            page.goto(url)
            page.wait_for_selector("body[data-figures-drawn]", timeout=60_000)
            out.append(time.perf_counter() - t)
        browser.close()
    return out


def flagged_report(base: str, stations: list[str], history: Any, drift: Any) -> bool:
    """Prints the out-of-control points; True when the drift is flagged."""
    from calstation.storage.dashboard import CHART_PARAMS

    params = "&".join(f"param={p}" for p in CHART_PARAMS)
    ok = True
    for station in stations:
        with urllib.request.urlopen(f"{base}/dashboard.json?station={station}&{params}",
                                    timeout=60) as r:
            d = json.loads(r.read())
        counts = ", ".join(f"{c['param']} {c['flagged']}/{len(c['points'])}"
                           for c in d["charts"])
        print(f"  {station}: out of control {counts}")
        if station != drift.station:
            continue
        chart = next(c for c in d["charts"] if c["param"] == drift.param)
        flagged = {p["run"] for p in chart["points"] if p["rules"]}
        drifting = [r for r in history.drifting if r in {p["run"] for p in chart["points"]}]
        hit = [r for r in drifting if r in flagged]
        first = next((p for p in chart["points"] if p["run"] in flagged and p["run"] in
                      set(drifting)), None)
        share = len(hit) / max(1, len(drifting))
        print(f"  seeded drift of {drift.param} on {station} "
              f"({drift.per_day * 1e3:.2f} mm a day from day {drift.start_day}): "
              f"{len(hit)} of {len(drifting)} drifting runs flagged ({100 * share:.0f} %)"
              + (f", the first at {first['t']} (run {first['run']}, rules {first['rules']})"
                 if first else ""))
        ok = ok and share >= 0.5
    return ok


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--stations", type=int, default=4)
    ap.add_argument("--weeks", type=int, default=8)
    ap.add_argument("--per-day", type=int, default=40)
    ap.add_argument("--drift-day", type=int, default=42)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--budget", type=float, default=1.5)
    args = ap.parse_args()

    from calstation.storage.db import open_database
    from calstation.testing.qa_history import Drift, seed_history
    from calstation.web.app import create_app

    stations = [f"station-{i + 1}" for i in range(args.stations)]
    drift = Drift(station=stations[min(2, len(stations) - 1)], start_day=args.drift_day)
    with tempfile.TemporaryDirectory(prefix="calstation-qa-") as tmp:
        db = open_database(f"sqlite:///{Path(tmp) / 'qa.db'}")
        t = time.perf_counter()
        history = seed_history(db, stations, 7 * args.weeks, args.per_day, drift=drift)
        n = sum(len(v) for v in history.runs.values())
        print(f"seeded {n} runs ({args.stations} stations × {args.weeks} weeks × "
              f"{args.per_day} a day) in {time.perf_counter() - t:.1f} s")
        app = create_app(db, data_dir=Path(tmp), recipes_dir=Path(tmp) / "recipes")
        base, server = serve(app)
        url = f"{base}/dashboard?days={7 * args.weeks}"
        server_times(url, 1)  # the first request imports the page's modules
        st, size = server_times(url, args.repeat)
        print(f"GET /dashboard: median {statistics.median(st):.3f} s (max {max(st):.3f} s), "
              f"{size / 1e6:.2f} MB")
        bt = browser_times(url, args.repeat)
        load = statistics.median(bt) if bt else statistics.median(st)
        if bt:
            print(f"dashboard in chromium, request to every figure drawn: median "
                  f"{statistics.median(bt):.3f} s (max {max(bt):.3f} s; each: "
                  f"{', '.join(f'{b:.2f}' for b in bt)} s)")
        else:
            print("chromium or Playwright missing: the browser's load is not measured")
        drift_ok = flagged_report(base, stations, history, drift)
        server.should_exit = True
        db.dispose()
    fast = load < args.budget
    print(f"load {load:.3f} s {'<' if fast else '≥'} {args.budget} s; drift "
          f"{'flagged' if drift_ok else 'NOT flagged'}")
    return 0 if fast and drift_ok else 1


if __name__ == "__main__":
    sys.exit(main())
