"""calstation: extrinsic calibration of a static line-scanning lidar over a rotary platform."""

from __future__ import annotations

import pluggy

from calstation import _compat

hookimpl = pluggy.HookimplMarker("calstation")
"""Marker for plugin hook implementations: ``from calstation import hookimpl``."""

_compat.install()


def __getattr__(name: str) -> str:
    """``__version__``: the installed distribution's version (from the git tag it was built
    from: setuptools-scm), read when first asked for; ``0+unknown`` when calstation runs from
    files that were never installed."""
    if name != "__version__":
        raise AttributeError(f"module 'calstation' has no attribute {name!r}")
    from importlib.metadata import PackageNotFoundError, version

    try:
        found = version("calstation")
    except PackageNotFoundError:
        found = "0+unknown"
    globals()["__version__"] = found
    return found


__all__ = ["__version__", "hookimpl"]
