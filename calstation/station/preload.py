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
    "calstation.engine.joint",
    "calstation.engine.fusion",
)
"""What :func:`preload_engine` imports in the background, in order: the fine-tuning, the cube
check, and the combination of the spin target with the cube (the cube step)."""


def import_open3d_first() -> None:
    """Import Open3D, if it can be, before anything that may import it without care: its import
    fails when another thread imports meanwhile (:func:`calstation.quiet.import_open3d`), and a
    driver's module (the simulator's) imports it at its top while other stations' runs import
    their engines. A missing Open3D is left to the step that needs it."""
    from calstation.quiet import import_open3d

    with suppress(ImportError):
        import_open3d()


def preload_engine() -> threading.Thread:
    """Import Open3D now, and the engine (fine-tuning, cube check) on a background thread while
    the operator places the targets and the scans run, so that no step after a scan waits for an
    import (~1.5 s together, Open3D ~0.8 s of it; it is imported once per process).

    Open3D first (:func:`import_open3d_first`), in the caller's thread and before the engine's
    imports begin. The caller imports nothing else until the thread ends (the station's steps
    that compute join it first: ``calstation.station.machine.WITHOUT_ENGINE``): two threads
    importing one module can deadlock in Python's import locks. A module that fails to import
    is left to fail with a clear error in the step that needs it."""
    import_open3d_first()

    def load() -> None:
        for name in ENGINE_MODULES:
            with suppress(Exception):
                importlib.import_module(name)

    thread = threading.Thread(target=load, name="calstation-preload", daemon=True)
    thread.start()
    return thread
