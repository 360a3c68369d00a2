"""The web station through FastAPI's test client: the app over a test database and the small
recipe of :mod:`tests.support.station`, the headers its page sends, and waits on its state."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from fastapi.testclient import TestClient

from calstation.storage.db import Database
from calstation.web.app import create_app
from tests.support.station import toy_recipe
from tests.support.webstation import wait_live

TOKEN = "station-token-0123456789"
"""The token of a station that listens beyond 127.0.0.1."""


def make_client(tmp_path: Path, db: Database, **kwargs: Any) -> TestClient:
    """The web station over ``db`` with the small recipe in ``tmp_path/recipes``; ``kwargs``:
    more arguments of ``create_app``."""
    recipes = tmp_path / "recipes"
    recipes.mkdir(exist_ok=True)
    toy_recipe(recipes)
    app = create_app(db, data_dir=tmp_path / "data", recipes_dir=recipes, **kwargs)
    return TestClient(app, base_url="http://127.0.0.1:8470")


ORIGIN = "http://127.0.0.1:8470"
"""The Origin a browser sends with the pages of :func:`make_client`."""


def csrf_of(client: TestClient) -> dict[str, str]:
    """Open the operator page like a browser; the headers the page's script sends with a
    state change (its CSRF value, and the Origin the browser adds)."""
    page = client.get("/")
    assert page.status_code == 200
    match = re.search(r'<meta name="csrf-token" content="([^"]+)">', page.text)
    assert match is not None
    return {"X-CSRF-Token": match.group(1), "Origin": ORIGIN}


def wait_prompt(client: TestClient, kind: str | None = None) -> dict[str, Any]:
    """The next prompt (of ``kind``), waited for on the station's changes, however long a
    loaded machine takes to get there."""
    def pending(st: dict[str, Any]) -> dict[str, Any] | None:
        p = st["prompt"]
        return p if p is not None and (kind is None or p["kind"] == kind) else None
    prompt: dict[str, Any] = wait_live(client, pending)
    return prompt


def finish(client: TestClient, headers: dict[str, str]) -> dict[str, Any]:
    """Answer Continue to every placement, and give up on a failed step (a failed cube check
    is one), until the run ends; the final state."""
    while True:
        st = client.get("/state.json").json()
        if not st["busy"]:
            return st
        if st["prompt"] and st["prompt"]["kind"] in ("fixture", "failure"):
            answer = "continue" if st["prompt"]["kind"] == "fixture" else "abort"
            r = client.post("/api/answer", headers=headers,
                            json={"prompt_id": st["prompt"]["id"], "answer": answer})
            # a snapshot read just before the run moved on holds a prompt that is no longer
            # pending: the server says so (409), and the page reloads, as this loop does
            assert r.status_code == 200 or (
                r.status_code == 409 and "is not pending" in r.text), r.text
            if r.status_code == 409:
                continue
        version = st["version"]
        wait_live(client, lambda s, v=version: s["version"] != v or not s["busy"])
