"""Helpers of the web station tests: the app over a test database, served for real by uvicorn in a
thread (for the browser tests), and the plugin set-up shared with the station tests."""

from __future__ import annotations

import os
import socket
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import uvicorn

from calstation.storage.db import Database, Run, Step
from tests.support.paths import REPO

DOCS_SHOTS = REPO / "docs" / "station"
"""Where the pictures of docs/station.md go (written with ``CALSTATION_DOCS_SCREENSHOTS=1``)."""

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--no-sandbox", "--disable-gpu", "--disable-background-networking",
    "--disable-component-update", "--disable-sync", "--no-first-run",
]


HANG_S = 900.0
"""How long a wait in these tests may last before it is taken for a hang: far longer than any
step takes on a loaded machine (a wait ends at its event, never at this)."""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextmanager
def served(app: Any, *, port: int | None = None, **config: Any) -> Iterator[str]:
    """Serve ``app`` on 127.0.0.1 with uvicorn in a thread, as ``calstation serve`` does (no
    ``Server`` banner); yields its base URL. ``config``: more ``uvicorn.Config`` arguments
    (``ssl_certfile``..., then the URL is https)."""
    port = port or free_port()
    config = {"log_level": "warning", "lifespan": "on", "timeout_graceful_shutdown": 2,
              "server_header": False, **config}
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, **config))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + HANG_S  # a hang guard: the wait ends when it serves
    while not server.started:
        if time.monotonic() > deadline or not thread.is_alive():
            raise RuntimeError("the test server did not start")
        time.sleep(0.05)
    try:
        yield f"{'https' if config.get('ssl_certfile') else 'http'}://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(30)


def run_status(db: Database, run_id: int) -> str:
    with db.session() as s:
        run = s.get(Run, run_id)
        assert run is not None
        return run.status


def steps_of(db: Database, run_id: int) -> list[tuple[str, int, str]]:
    with db.session() as s:
        return [(r.name, r.attempt, r.status)
                for r in s.query(Step).filter_by(run_id=run_id).order_by(Step.id)]


def wait_live(client: Any, predicate: Any, hang_s: float = HANG_S) -> Any:
    """Wait on the web station's live state (its condition, notified at every change) until
    ``predicate(snapshot)`` is truthy, and return that. Fails at once when the run has ended
    and the predicate still does not hold (it never will), and after ``hang_s`` only as a
    hang guard."""
    live = client.app.state.runner.live
    deadline = time.monotonic() + hang_s
    with live._cond:
        while True:
            snapshot = live.snapshot()
            value = predicate(snapshot)
            if value:
                return value
            if not snapshot["busy"] and not client.app.state.runner.busy:
                raise AssertionError(f"the run ended without {predicate}: {snapshot['status']}, "
                                     f"{snapshot['error']}, log {snapshot['log'][-5:]}")
            if not live._cond.wait(timeout=max(0.0, deadline - time.monotonic())):
                raise AssertionError(f"no change of the station in {hang_s:g} s (a hang?)")


def wait_until(predicate: Any, timeout: float = HANG_S, period: float = 0.1) -> Any:
    """Poll ``predicate`` until it returns something truthy; fails after ``timeout`` s (a hang
    guard: the wait ends when the predicate holds)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(period)
    raise AssertionError(f"timed out after {timeout} s waiting for {predicate}")


def copy_recipe(src: Path, folder: Path, name: str | None = None) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    dst = folder / (name or src.name)
    dst.write_text(src.read_text(encoding="utf-8"), encoding="utf-8")
    return dst


def shot(page: Any, name: str, full: bool = False, *, colours: int = 96,
         max_width: int | None = None, octree: bool = False) -> None:
    """A picture for docs/station.md, ``docs/station/<name>.png`` (only with
    ``CALSTATION_DOCS_SCREENSHOTS=1``), reduced to a palette of ``colours`` and, when wider,
    scaled to ``max_width`` pixels so the repository stays small. ``octree``: the palette by
    octree, which keeps the colour of a few pixels (a cloud's highest points) where the median
    cut merges it into a frequent one."""
    if os.environ.get("CALSTATION_DOCS_SCREENSHOTS") != "1":
        return
    from PIL import Image

    DOCS_SHOTS.mkdir(parents=True, exist_ok=True)
    path = DOCS_SHOTS / f"{name}.png"
    page.screenshot(path=str(path), full_page=full)
    with Image.open(path) as image:
        method = Image.Quantize.FASTOCTREE if octree else None
        small = image.convert("RGB").quantize(colors=colours, method=method)
        if max_width is not None and small.width > max_width:
            small = small.resize((max_width, round(small.height * max_width / small.width)))
    small.save(path, optimize=True)
