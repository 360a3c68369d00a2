"""The guided run of a recipe: the state machine (:mod:`calstation.station.machine`), one
module per step (:mod:`calstation.station.steps`), and creating, starting and resuming runs
(:mod:`calstation.station.runs`). docs/architecture.md says where each part lives.

The names the flat module ``calstation.station`` had (``start_run``, ``resume_run``,
``create_run``, ``wait_for_step``, ``Station``, ``STEPS``, …) still import from here for one
release, with a :class:`DeprecationWarning` that names their new module.
"""

from __future__ import annotations

import importlib
import warnings

_MOVED_NAMES = {
    "Station": "calstation.station.machine",
    "STEPS": "calstation.station.steps",
    "run_steps": "calstation.station.steps",
    "StepOutcome": "calstation.station.outcome",
    "create_run": "calstation.station.runs",
    "start_run": "calstation.station.runs",
    "resume_run": "calstation.station.runs",
    "resumable_run": "calstation.station.runs",
    "wait_for_step": "calstation.station.runs",
    "data_dir_default": "calstation.station.runs",
    "preload_engine": "calstation.station.preload",
    "checked_recording": "calstation.station.stored",
    "file_sha256": "calstation.recordings.runfolder",
    "AbortRun": "calstation.errors",
}


def __getattr__(name: str) -> object:
    module = _MOVED_NAMES.get(name)
    if module is None:
        raise AttributeError(f"module 'calstation.station' has no attribute {name!r}")
    warnings.warn(f"calstation.station.{name} moved to {module}.{name}; the old import path "
                  "will be removed in the next calstation release", DeprecationWarning,
                  stacklevel=2)
    return getattr(importlib.import_module(module), name)
