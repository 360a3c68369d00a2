"""calstation: extrinsic calibration of a static line-scanning lidar over a rotary platform."""

from __future__ import annotations

import pluggy

from calstation import _compat

__version__ = "0.1.0"

hookimpl = pluggy.HookimplMarker("calstation")
"""Marker for plugin hook implementations: ``from calstation import hookimpl``."""

_compat.install()

__all__ = ["__version__", "hookimpl"]
