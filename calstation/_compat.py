"""Old import paths, kept for one release.

calstation's modules moved into packages (docs/architecture.md). A plugin that still imports an
old path, ``from calstation.recipe import load_recipe`` say, gets the module at its new place,
the very same module object, with a :class:`DeprecationWarning` that names the new path. The
next release removes the old paths.

The finder is installed by ``calstation/__init__.py``, ahead of the other finders, so that the
old name never imports a second copy of a module.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import sys
import warnings
from types import ModuleType

MOVED: dict[str, str] = {
    "calstation.frames": "calstation.engine.frames",
    "calstation.binning": "calstation.engine.binning",
    "calstation.lines": "calstation.engine.lines",
    "calstation.neighbours": "calstation.engine.neighbours",
    "calstation.geometry": "calstation.engine.geometry",
    "calstation.initial": "calstation.engine.initial",
    "calstation.periodicity": "calstation.engine.periodicity",
    "calstation.shape": "calstation.engine.shape",
    "calstation.cube": "calstation.engine.cube",
    "calstation.joint": "calstation.engine.joint",
    "calstation.timeoffset": "calstation.engine.timeoffset",
    "calstation.targetless": "calstation.engine.targetless",
    "calstation.observability": "calstation.engine.observability",
    "calstation.metrics": "calstation.engine.metrics",
    "calstation.reconstruct": "calstation.engine.reconstruct",
    "calstation.spinscan": "calstation.engine.spinscan",
    "calstation.result": "calstation.engine.result",
    "calstation.recording": "calstation.recordings.recording",
    "calstation.messages": "calstation.recordings.messages",
    "calstation.protowire": "calstation.recordings.protowire",
    "calstation.mcapscan": "calstation.recordings.mcapscan",
    "calstation.liveview": "calstation.recordings.liveview",
    "calstation.runfolder": "calstation.recordings.runfolder",
    "calstation.replay": "calstation.recordings.replay",
    "calstation.recipe": "calstation.recipes",
    "calstation.hookspecs": "calstation.plugins.hookspecs",
    "calstation.strategies": "calstation.plugins.cost_strategies",
    "calstation.builtin_plugins": "calstation.plugins.builtin",
    "calstation.builtin_plugins.strategies": "calstation.plugins.builtin.strategies",
    "calstation.builtin_plugins.replay": "calstation.plugins.builtin.replay",
    "calstation.db": "calstation.storage.db",
    "calstation.db.models": "calstation.storage.db.models",
    "calstation.db.journal": "calstation.storage.db.journal",
    "calstation.report": "calstation.storage.report",
    "calstation.report_html": "calstation.storage.report_html",
    "calstation.ros": "calstation.storage.ros",
    "calstation.web.templating": "calstation.storage.templating",
    "calstation.web.qa": "calstation.storage.qa",
    "calstation.operator": "calstation.station.operator",
    "calstation.acquisition": "calstation.station.acquisition",
    "calstation.reprocess": "calstation.station.reprocess",
}
"""Old module path → where it lives now."""


class _Alias(importlib.abc.Loader):
    def __init__(self, module: ModuleType) -> None:
        self.module = module
        self.spec = module.__spec__

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> ModuleType:
        return self.module

    def exec_module(self, module: ModuleType) -> None:
        # the import machinery stamped the old name's spec on the module: give it its own back
        module.__spec__ = self.spec
        sys.modules[module.__name__] = module


class MovedModuleFinder(importlib.abc.MetaPathFinder):
    """Finds the old paths of :data:`MOVED`; warns and hands out the module's new place."""

    def find_spec(
        self, fullname: str, path: object = None, target: object = None
    ) -> importlib.machinery.ModuleSpec | None:
        new = MOVED.get(fullname)
        if new is None:
            return None
        warnings.warn(
            f"{fullname} moved to {new}; the old import path will be removed in the next "
            "calstation release",
            DeprecationWarning,
            stacklevel=_caller_level(),
        )
        module = importlib.import_module(new)
        return importlib.machinery.ModuleSpec(
            fullname, _Alias(module), is_package=hasattr(module, "__path__")
        )


def _caller_level() -> int:
    """The stack level of the code that wrote the import: past this module's frames
    (:func:`warnings.warn` itself skips the import machinery's)."""
    frame = sys._getframe(1)
    level = 1
    while frame is not None:
        name = frame.f_code.co_filename
        if not ("importlib" in name and "_bootstrap" in name):
            if name != __file__:
                return level
            level += 1
        frame = frame.f_back  # type: ignore[assignment]
    return level


def install() -> None:
    """Put the finder first on ``sys.meta_path`` (once)."""
    if not any(isinstance(f, MovedModuleFinder) for f in sys.meta_path):
        sys.meta_path.insert(0, MovedModuleFinder())
