"""Importing the engine ahead of need: a run starts it on a background thread while the operator
places the targets and the scans run, so that no step after a scan waits for an import."""

from __future__ import annotations

import importlib
import threading
from contextlib import suppress

ENGINE_MODULES = (
    "calstation.engine.periodicity",
    "calstation.engine.shape",
    "calstation.engine.cube",
    "open3d",
)
"""What :func:`preload_engine` imports, in order: the fine-tuning, the cube check, Open3D."""


def preload_engine() -> threading.Thread:
    """Import the engine (fine-tuning, cube check, Open3D) on a background thread while the
    operator places the targets and the scans run, so that no step after a scan waits for an
    import (~1.5 s together, Open3D ~0.8 s of it). A module that fails to import is left to
    fail with a clear error in the step that needs it."""

    def load() -> None:
        for name in ENGINE_MODULES:
            with suppress(Exception):
                importlib.import_module(name)

    thread = threading.Thread(target=load, name="calstation-preload", daemon=True)
    thread.start()
    return thread
