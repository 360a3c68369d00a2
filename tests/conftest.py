"""The fixtures every layer's tests share (a layer's own are in its folder's conftest.py; the
helpers the tests import are in tests/support/)."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest
from hypothesis import HealthCheck, settings

from tests.support.paths import REPO

if TYPE_CHECKING:
    from calstation.storage.db import Database
    from tests.support.station import StationTestPlugin

os.environ.setdefault("MPLBACKEND", "Agg")

# CI (.ci/run) draws the same property-test examples on every run, so a landing is judged on the
# code and not on the draw; a local run draws new ones each time and keeps what fails in
# .hypothesis/ to replay it. Neither times an example or its drawing: on a loaded machine (CI's
# runners, `make test-stress`) a deadline or the "too slow" health check fails a test for the
# machine's speed, not for the code.
UNTIMED = {"deadline": None, "suppress_health_check": [HealthCheck.too_slow]}
settings.register_profile("default", **UNTIMED)  # type: ignore[arg-type]
settings.register_profile("ci", derandomize=True, print_blob=True,
                          **UNTIMED)  # type: ignore[arg-type]
settings.load_profile(os.environ.get("CALSTATION_HYPOTHESIS_PROFILE", "default"))


@pytest.fixture(scope="session")
def sim_run(tmp_path_factory: pytest.TempPathFactory) -> Callable[..., dict[str, Path]]:
    """Factory of simulated runs, each simulated once per argument set per test session.

    ``sim_run(range_m=1.25, pitch_deg=45.0, seed=1, recipe="recipes/sim-periodicity.yaml")``
    returns ``{"static", "spin", "cube", "truth"}`` → paths (``calstation_sim.simulate_run``);
    ``recipe`` is relative to the repository root (or absolute). Treat the files as read-only:
    other tests share them.
    """
    cache: dict[tuple[float, float, int, str], dict[str, Path]] = {}

    def run(
        range_m: float = 1.25,
        pitch_deg: float = 45.0,
        seed: int = 1,
        recipe: str | Path = "recipes/sim-periodicity.yaml",
    ) -> dict[str, Path]:
        from calstation_sim import simulate_run

        from calstation.recipes import load_recipe

        path = Path(recipe) if Path(recipe).is_absolute() else REPO / recipe
        key = (float(range_m), float(pitch_deg), int(seed), str(path))
        if key not in cache:
            out = tmp_path_factory.mktemp(f"sim-r{range_m:g}-p{pitch_deg:g}-s{seed}")
            cache[key] = simulate_run(
                load_recipe(path),
                out,
                seed=seed,
                range_m=range_m,
                pitch_deg=pitch_deg,
                progress=False,
            )
        return dict(cache[key])

    return run


@pytest.fixture(scope="session")
def fleet_sim(tmp_path_factory: pytest.TempPathFactory) -> Any:
    """Two simulated runs of the fleet recipe and what today's engine finds on each
    (:func:`calstation.testing.fleet.simulate_fleet`): what the campaign tests seed runs on.
    Treat the files as read-only: other tests share them."""
    from calstation.testing.fleet import simulate_fleet

    return simulate_fleet(tmp_path_factory.mktemp("fleet"))


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    """Debian's chromium under Playwright, one per test module (a module that needs other
    launch options defines its own)."""
    playwright_api = pytest.importorskip("playwright.sync_api")
    from tests.support.webstation import CHROMIUM, CHROMIUM_ARGS

    with playwright_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield b
        b.close()


@pytest.fixture
def db(tmp_path: Path) -> Iterator[Database]:
    """A new SQLite run database in the test's folder."""
    from calstation.storage.db import open_database

    database = open_database(f"sqlite:///{tmp_path / 'test.db'}")
    yield database
    database.dispose()


@pytest.fixture
def station_plugin() -> Iterator[StationTestPlugin]:
    """The simulator and :class:`tests.support.station.StationTestPlugin` (spy drivers, the toy
    strategy, an observer) as the only plugins while the test runs."""
    from calstation import plugins

    sim_plugin = pytest.importorskip("calstation_sim.plugin")
    from tests.support.station import StationTestPlugin

    plugin = StationTestPlugin()
    with plugins.isolated(sim_plugin, plugin):
        yield plugin


@pytest.fixture(scope="module")
def postgres_url() -> Iterator[str]:
    """A throw-away PostgreSQL server (Debian's postgresql package) in a temporary folder, one
    per test module; skips the test when psycopg is missing or no server can be started (as
    root, the server runs as user ``postgres``; ``calstation.testing.postgres``)."""
    pytest.importorskip("psycopg")
    from calstation.testing.postgres import NoPostgres, throwaway_postgres

    with ExitStack() as stack:
        try:
            url = stack.enter_context(throwaway_postgres())
        except NoPostgres as exc:
            pytest.skip(str(exc))
        yield url
