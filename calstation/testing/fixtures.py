"""pytest fixtures for strategy tests: the recordings of a simulated run, made once per session.

Enable them in a plugin's ``tests/conftest.py``::

    from calstation.testing.fixtures import simulated_scans, strategy_start  # noqa: F401

(or ``pytest_plugins = ["calstation.testing.fixtures"]`` in a top-level conftest).

and use them in a test::

    def test_my_strategy(simulated_scans, strategy_start):
        result, warnings = run_strategy(MyStrategy(), read_recording(simulated_scans.cube),
                                        strategy_start, simulated_scans.recipe.recipe)

The scans come from the ``calstation-sim`` plugin; without it the tests using them are skipped.
"""

from __future__ import annotations

import pytest

from calstation.engine.frames import Extrinsics
from calstation.testing import SimulatedScans, simulate_scans, strategy_start as _strategy_start


@pytest.fixture(scope="session")
def simulated_scans(tmp_path_factory: pytest.TempPathFactory) -> SimulatedScans:
    """A simulated run of the shipped ``sim-periodicity`` recipe (1.25 m, 45°, seed 1); the test
    is skipped without a simulator (``pip install 'calstation[sim]'``)."""
    from calstation import plugins
    from calstation.plugins.simulation import DEFAULT_SIMULATOR

    if DEFAULT_SIMULATOR not in plugins.simulators():
        pytest.skip("simulated scans need the calstation-sim plugin")
    return simulate_scans(tmp_path_factory.mktemp("calstation-scans"))


@pytest.fixture(scope="session")
def strategy_start(simulated_scans: SimulatedScans) -> Extrinsics:
    """The initial calibration of :func:`simulated_scans`' static scan (a strategy's start)."""
    return _strategy_start(simulated_scans)
