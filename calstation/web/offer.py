"""What the operator page's start form offers: the recipes that can run (a template, or a recipe
that does not validate, is listed as such and cannot be chosen), and the recipe and operator of
the last run started from the recipes folder as the defaults."""

from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from calstation.errors import CalstationError, StationError
from calstation.storage.db import Database, Run

if TYPE_CHECKING:
    from calstation.recipes import Recipe

TEMPLATE_WORD = "template"
"""A recipe whose name (or file name) says so is a template, to be copied and filled in before
it runs (``recipes/real-station-template.yaml``)."""


@dataclass(frozen=True)
class Choice:
    """One recipe file of the folder: whether it can run, and if not why; its station, its
    description and the seconds its scans turn (what the start form says of it)."""

    name: str
    why_not: str | None = None
    station: str | None = None
    description: str = ""
    scan_s: float | None = None
    simulated: bool = False
    """every driver is the simulator's"""

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
    r = loaded.recipe
    drivers = (r.station.lidar.driver, r.station.turntable.driver, r.station.encoder.driver)
    return Choice(path.name, station=r.station.id, description=" ".join(r.description.split()),
                  scan_s=scan_seconds(r), simulated=all(d == "sim" for d in drivers))


def scan_seconds(recipe: Recipe) -> float:
    """How long a run of ``recipe`` turns the platter at the least: the spin and cube scans'
    turns at their speeds, second passes included (what an operator waits for at best)."""
    total = 0.0
    for scan in (recipe.steps.spin_scan, recipe.steps.cube_scan):
        second = scan.second_pass()
        passes = [scan] + ([second] if second is not None else [])
        total += sum(60.0 * p.revolutions / abs(p.rpm) for p in passes)
    return total


def offered(choices: list[Choice]) -> list[Choice]:
    """The runnable recipes in the order the start form offers them: simulated stations
    first, then by how long their scans turn, then by name (the quickest run first)."""
    return sorted((c for c in choices if c.runnable),
                  key=lambda c: (not c.simulated, c.scan_s or 0.0, c.name))


def refuse_unrunnable(path: Path) -> None:
    """:class:`StationError` naming why the recipe file ``path`` cannot run, if it cannot."""
    choice = judge(path)
    if not choice.runnable:
        raise StationError(f"recipe {choice.name} cannot run: {choice.why_not}")


def start_defaults(db: Database, recipes_dir: Path, runnable: list[str]
                   ) -> dict[str, str | None]:
    """The recipe of the newest run started from a recipe of ``recipes_dir`` (runnable still),
    else the first of ``runnable`` (the quickest, :func:`offered`). The operator is left to
    the browser, which remembers who used it: the newest run's operator may be someone else's
    name, or a terminal's login name."""
    from sqlalchemy import select

    recipe = runnable[0] if runnable else None
    folder = str(recipes_dir.resolve())
    with db.session("reading the runs", read_only=True) as s:
        rows = s.execute(select(Run.recipe_path).order_by(Run.id.desc()).limit(50)).all()
    for (path,) in rows:
        if path and str(Path(path).resolve().parent) == folder and Path(path).name in runnable:
            recipe = Path(path).name
            break
    return {"recipe": recipe}
