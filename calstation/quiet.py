"""Keeping libraries' chatter off standard output.

Open3D prints its warnings through Python's ``sys.stdout`` (and C++ code may write to file
descriptor 1), ahead of any JSON a command prints. :func:`stdout_to_stderr` points both at
standard error while a library works;
:func:`quiet_open3d` also lowers Open3D's verbosity to errors.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager, redirect_stdout, suppress
from typing import Any


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


@contextmanager
def quiet_open3d() -> Iterator[Any]:
    """Open3D, imported, with its messages limited to errors and kept off standard output."""
    with stdout_to_stderr():
        import open3d as o3d

        o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
        yield o3d
