"""Fixtures of the web station's tests."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from tests.support.webpage import FAILURES
from tests.support.webstation import HANG_S


@pytest.fixture
def page(browser: Any, request: pytest.FixtureRequest) -> Iterator[Any]:
    """A page of its own in the module's browser; dialogs are accepted ("Abort the run?" → yes),
    and a failing test leaves its screenshot in ``FAILURES`` (a module that needs another page
    defines its own)."""
    context = browser.new_context(viewport={"width": 1200, "height": 860})
    pg = context.new_page()
    pg.set_default_timeout(HANG_S * 1000)  # a hang guard: waits end at their event
    pg.on("dialog", lambda d: d.accept())  # "Abort the run?" → yes
    failed_before = request.session.testsfailed
    yield pg
    if request.session.testsfailed > failed_before:  # counted before this teardown
        FAILURES.mkdir(parents=True, exist_ok=True)
        pg.screenshot(path=str(FAILURES / f"{request.node.name}.png"), full_page=True)
    context.close()
