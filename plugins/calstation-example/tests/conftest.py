"""The plugin author's kit: simulated scans for the strategy tests."""

pytest_plugins = ["calstation.testing.fixtures"]
