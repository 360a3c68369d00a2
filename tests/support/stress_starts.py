"""One fresh process of the start-up stress test (tests/web/test_web_stress.py): several web
stations over one database start a run at the same moment while event streams connect and
disconnect and another thread imports modules (as another station's engine is imported when its
run starts), with Python's thread switch interval made tiny so that the threads interleave far
more often than on a quiet machine. Prints one JSON line: each run's status at its first prompt
and the errors its page logged. A fresh process, because a module is imported once per process:
the first runs are the ones that import.

    python tests/support/stress_starts.py STATIONS [HANG_GUARD_S]
"""

from __future__ import annotations

import json
import re
import sys
import tempfile
import threading
from pathlib import Path

sys.setswitchinterval(1e-5)  # threads switch every 10 µs instead of 5 ms

import yaml  # noqa: E402
from fastapi.testclient import TestClient  # noqa: E402

from calstation import plugins  # noqa: E402
from calstation.storage.db import open_database  # noqa: E402
from calstation.web.app import create_app  # noqa: E402

ORIGIN = "http://127.0.0.1:8470"
RECIPE = Path(__file__).resolve().parents[2] / "recipes" / "sim-periodicity.yaml"


def _station(tmp: Path, db: object, k: int) -> TestClient:
    """Web station ``k``: the simulated recipe on a station of its own (the simulator's drivers
    are imported, as in ``calstation serve``, when its first run opens them)."""
    recipes = tmp / f"recipes-{k}"
    recipes.mkdir()
    data = yaml.safe_load(RECIPE.read_text())
    data["station"]["id"] = f"stress-{k}"
    data["simulation"]["lidar"]["points_per_line"] = 500
    (recipes / "lean.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    return TestClient(create_app(db, data_dir=tmp / "data", recipes_dir=recipes),  # type: ignore[arg-type]
                      base_url=ORIGIN)


def _streams(client: TestClient, stop: threading.Event) -> None:
    """Open the event stream, read its first state, close it; again, until told to stop."""
    while not stop.is_set():
        try:
            with client.stream("GET", "/events") as r:
                for _ in r.iter_bytes():
                    break
        except Exception:  # a stream cut by the test client's shutdown
            return


def _import_others(stop: threading.Event) -> None:
    """Import modules not imported yet, one after the other, until told to stop."""
    import importlib
    import pkgutil

    import scipy

    for info in pkgutil.walk_packages(scipy.__path__, "scipy."):
        if stop.is_set():
            return
        if "test" not in info.name:
            try:
                importlib.import_module(info.name)
            except Exception:  # optional parts of SciPy
                continue


def main(stations: int) -> dict[str, object]:
    from calstation_sim import plugin as sim_plugin

    tmp = Path(tempfile.mkdtemp(prefix="calstation-stress-"))
    with plugins.isolated(sim_plugin):
        db = open_database(f"sqlite:///{tmp / 'web.db'}")
        clients = [_station(tmp, db, k) for k in range(stations)]
        headers = []
        for c in clients:
            c.__enter__()
            token = re.search(r'<meta name="csrf-token" content="([^"]+)">', c.get("/").text)
            assert token is not None
            headers.append({"X-CSRF-Token": token.group(1), "Origin": ORIGIN})
        stop = threading.Event()
        readers = [threading.Thread(target=_streams, args=(c, stop), daemon=True)
                   for c in clients for _ in range(3)]
        readers.append(threading.Thread(target=_import_others, args=(stop,), daemon=True))
        for t in readers:
            t.start()
        together = threading.Barrier(stations)
        answers: dict[int, int] = {}

        def start(k: int) -> None:
            together.wait()
            answers[k] = clients[k].post("/api/start", headers=headers[k],
                                         json={"recipe": "lean.yaml", "operator": "ann"}
                                         ).status_code

        starters = [threading.Thread(target=start, args=(k,)) for k in range(stations)]
        for t in starters:
            t.start()
        for t in starters:
            t.join()
        runs = []
        for k, c in enumerate(clients):
            live = c.app.state.runner.live  # type: ignore[attr-defined]
            with live._cond:  # an event: the first prompt, or the end of the run
                live._cond.wait_for(lambda lv=live: lv.prompt is not None
                                    or lv.status != "running")
            runs.append({"station": k, "started": answers.get(k), "status": live.status,
                         "prompt": live.prompt is not None,
                         "errors": [e["text"] for e in live.log if e["level"] == "error"]})
            c.app.state.runner.abort("the stress test is done")  # type: ignore[attr-defined]
            c.app.state.runner.join()  # type: ignore[attr-defined]
        stop.set()
        for t in readers:
            t.join()
        for c in clients:
            c.__exit__(None, None, None)
        db.dispose()
    return {"runs": runs}


if __name__ == "__main__":
    import faulthandler

    # a hang shows where every thread is, then ends the process (the test reports it)
    faulthandler.dump_traceback_later(float(sys.argv[2]) if len(sys.argv) > 2 else 240.0,
                                      exit=True)
    print(json.dumps(main(int(sys.argv[1]))), flush=True)
