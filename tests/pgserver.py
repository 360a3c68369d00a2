"""A throw-away PostgreSQL server for tests, from Debian's postgresql package when installed.

Use as a fixture: ``postgres_url = pgserver.postgres_url`` in a test module. Skips the test when
psycopg is missing or no server can be started (as root, the server runs as user ``postgres``;
:func:`calstation.testing.postgres.throwaway_postgres`).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import ExitStack

import pytest

from calstation.testing.postgres import NoPostgres, throwaway_postgres


@pytest.fixture(scope="module")
def postgres_url() -> Iterator[str]:
    """Start a private PostgreSQL server in a temporary folder; skip when that is impossible."""
    pytest.importorskip("psycopg")
    with ExitStack() as stack:
        try:
            url = stack.enter_context(throwaway_postgres())
        except NoPostgres as exc:
            pytest.skip(str(exc))
        yield url
