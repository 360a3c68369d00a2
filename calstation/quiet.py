"""Keeping libraries' chatter off standard output, and importing Open3D safely.

Open3D prints its warnings through Python's ``sys.stdout`` (and C++ code may write to file
descriptor 1), ahead of any JSON a command prints. :func:`stdout_to_stderr` points both at
standard error while a library works;
:func:`quiet_open3d` also lowers Open3D's verbosity to errors. :func:`import_open3d` is how
calstation imports Open3D the first time in a process with other threads.
"""

from __future__ import annotations

import os
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager, redirect_stdout, suppress
from types import ModuleType


def _flush_c_stdout() -> None:
    with suppress(OSError, AttributeError):
        import ctypes

        ctypes.CDLL(None).fflush(None)


@contextmanager
def stdout_to_stderr() -> Iterator[None]:
    """Send whatever is written to descriptor 1 (C libraries included) to standard error."""
    try:
        sys.stdout.flush()
        saved = os.dup(1)
    except (OSError, ValueError):  # no real descriptor 1 (embedded use): Python's stdout only
        with redirect_stdout(sys.stderr):
            yield
        return
    try:
        os.dup2(2, 1)
        # Open3D's Python bindings print through Python's sys.stdout, C++ code to descriptor 1
        with redirect_stdout(sys.stderr):
            yield
    finally:
        with suppress(OSError, ValueError):
            sys.stdout.flush()
        _flush_c_stdout()  # C libraries buffer: flush while descriptor 1 is still stderr
        os.dup2(saved, 1)
        os.close(saved)


_OPEN3D_LOCK = threading.Lock()

OPEN3D_ATTEMPTS = 20
"""Times the first import of Open3D is tried while other threads keep importing."""


def import_open3d() -> ModuleType:
    """The ``open3d`` module, imported safely while other threads import modules.

    The last step of ``open3d/__init__.py`` walks ``sys.modules`` itself; another thread
    importing any module during that walk makes the import fail with ``RuntimeError:
    dictionary changed size during iteration`` (two web stations starting runs at once: one
    station's driver imported Open3D while the other's engine was being imported, and its run
    failed at its start). The modules the failed import loaded stay loaded, so importing again
    only repeats the walk: this does, a few times, one thread at a time.
    """
    with _OPEN3D_LOCK:
        for attempt in range(1, OPEN3D_ATTEMPTS + 1):
            try:
                import open3d

                return open3d
            except RuntimeError as exc:
                if "changed size during iteration" not in str(exc) or attempt == OPEN3D_ATTEMPTS:
                    raise
    raise AssertionError("not reached")  # pragma: no cover


@contextmanager
def quiet_open3d() -> Iterator[ModuleType]:
    """Open3D, imported, with its messages limited to errors and kept off standard output."""
    with stdout_to_stderr():
        o3d = import_open3d()

        o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
        yield o3d
