"""What the operator page's start form offers: the recipes that can run (a template, or a recipe
that does not validate, is listed as such and cannot be chosen), and the recipe and operator of
the last run started from the recipes folder as the defaults."""

from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from calstation.errors import CalstationError, StationError
from calstation.storage.db import Database, Run

TEMPLATE_WORD = "template"
"""A recipe whose name (or file name) says so is a template, to be copied and filled in before
it runs (``recipes/real-station-template.yaml``)."""


@dataclass(frozen=True)
class Choice:
    """One recipe file of the folder: whether it can run, and if not why."""

    name: str
    why_not: str | None = None

    @property
    def runnable(self) -> bool:
        """Whether the start form offers it."""
        return self.why_not is None


_cache: dict[tuple[str, float, int], Choice] = {}
_cache_lock = threading.Lock()


def judge(path: Path) -> Choice:
    """Whether the recipe file ``path`` can run: not a template, and it validates (recipe and
    plugins). Cached by the file's modification time and size."""
    stat = path.stat()
    key = (str(path), stat.st_mtime, stat.st_size)
    with _cache_lock:
        if key in _cache:
            return _cache[key]
    choice = _judge(path)
    with _cache_lock:
        _cache[key] = choice
    return choice


def _judge(path: Path) -> Choice:
    from calstation.plugins.recipe_checks import check_plugins
    from calstation.recipes import load_recipe

    template = Choice(path.name, "it is a template: copy it, fill in its FIXME values and give "
                                 "the copy a name of its own")
    if TEMPLATE_WORD in path.stem.lower():
        return template
    try:
        loaded = load_recipe(path)
        check_plugins(loaded)
    except CalstationError as exc:
        said = " ".join(str(exc).split()) or type(exc).__name__
        return Choice(path.name, f"it does not validate: {said[:300]}")
    if TEMPLATE_WORD in loaded.recipe.name.lower():
        return template
    return Choice(path.name)


def refuse_unrunnable(path: Path) -> None:
    """:class:`StationError` naming why the recipe file ``path`` cannot run, if it cannot."""
    choice = judge(path)
    if not choice.runnable:
        raise StationError(f"recipe {choice.name} cannot run: {choice.why_not}")


def start_defaults(db: Database, recipes_dir: Path, runnable: list[str]) -> dict[str, Any]:
    """The recipe and operator of the newest run started from a recipe of ``recipes_dir``
    (runnable still), else the first runnable recipe and no operator."""
    from sqlalchemy import select

    recipe, operator = (runnable[0] if runnable else None), ""
    folder = str(recipes_dir.resolve())
    with db.session("reading the runs", read_only=True) as s:
        rows = s.execute(select(Run.recipe_path, Run.operator).order_by(Run.id.desc())
                         .limit(50)).all()
    for path, who in rows:
        if path and str(Path(path).resolve().parent) == folder and Path(path).name in runnable:
            recipe, operator = Path(path).name, who
            break
    return {"recipe": recipe, "operator": operator[:100]}
