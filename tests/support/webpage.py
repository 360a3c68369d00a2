"""The web station's pages in a real browser (Playwright): the app served for a test, and the
clicks an operator makes (start a run, answer a placement prompt, wait for the verdict)."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from calstation.storage.db import Database
from calstation.web.app import create_app
from tests.support.paths import REPO
from tests.support.webstation import served

FAILURES = Path(os.environ.get("CALSTATION_TEST_SCREENSHOTS", REPO / "out" / "browser-failures"))


@contextmanager
def station(tmp_path: Path, db: Database, recipe: Path) -> Iterator[str]:
    app = create_app(db, data_dir=tmp_path / "data", recipes_dir=recipe.parent)
    with served(app) as url:
        yield url


def start(page: Any, url: str, recipe: str, operator: str = "ann", serial: str = "") -> None:
    page.goto(url + "/")
    page.select_option("#recipe", recipe)
    page.fill("#operator", operator)
    page.fill("#serial", serial)
    page.click("#start-button")
    page.wait_for_selector("#run:not([hidden])")


def place(page: Any, fixture: str) -> Any:
    """Wait for the placement prompt of ``fixture``; returns the prompt box."""
    return page.wait_for_selector(f'#prompt:not([hidden])[data-fixture="{fixture}"]'
                                  '[data-kind="fixture"]')


def click_answer(page: Any, answer: str) -> None:
    page.click(f'#prompt button[data-answer="{answer}"]:not([hidden])')


def wait_end(page: Any) -> str:
    verdict = page.wait_for_selector("#verdict")
    return str(verdict.inner_text())
