"""The plugin author's kit: simulated scans for the strategy tests.

Importing the fixtures works in a plugin's own repository and inside calstation's (where pytest
refuses ``pytest_plugins`` in a conftest below the root).
"""

from calstation.testing.fixtures import simulated_scans, strategy_start

__all__ = ["simulated_scans", "strategy_start"]
