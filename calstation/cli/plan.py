"""``calstation plan RECIPE``: what a station design can reach, before the hardware exists."""

from __future__ import annotations

import json
import math
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from calstation.jsonvalue import JSONValue

if TYPE_CHECKING:
    from types import TracebackType

    from rich.console import Console
    from rich.status import Status

    from calstation.bench.plan import ByTurns, Plan
    from calstation.recipes import LoadedRecipe


def register(app: typer.Typer) -> None:
    """Add the ``plan`` command."""

    @app.command("plan")
    def plan_cmd(
        recipe: Path = typer.Argument(..., help="The station's recipe, with a simulation "
                                      "section describing it.", show_default=False),
        seeds: int = typer.Option(1, "--seeds", min=1, max=20,
                                  help="Simulated stations (noise draws) per figure."),
        turns: int = typer.Option(2, "--turns", min=1, max=8,
                                  help="Turns of the simulated spin scans (1 … N are fitted)."),
        alternatives: bool = typer.Option(True, "--alternatives/--no-alternatives",
                                          help="Also try the spin target's placement and "
                                          "height."),
        overrides: list[str] = typer.Option(
            [], "--set", metavar="KEY=VALUE",
            help="Change a recipe field for the plan: --set simulation.lidar.range_noise=0.002 "
            "(repeatable; values are YAML).",
        ),
        as_json: bool = typer.Option(False, "--json", help="Print the plan as JSON."),
        cache: bool = typer.Option(True, "--cache/--no-cache",
                                   help="Keep the simulated scans in $CALSTATION_HOME/plan-cache "
                                   "and take them from there when the same station is planned "
                                   "again."),
    ) -> None:
        """Simulate RECIPE's station and print, per parameter, the σ the fine-tuning states,
        the predicted reconstruction error over the work volume against the recipe's budget
        (calibration.accuracy), how it falls with the turns, the turns the budget needs, and
        which placement or height of the spin target helps."""
        from rich.console import Console

        from calstation.bench.plan import cache_folder, plan
        from calstation.quiet import stdout_to_stderr

        loaded = _loaded(recipe, overrides)
        console = Console(stderr=True)
        with PlanProgress(console) as progress, stdout_to_stderr():
            result = plan(loaded, seeds=seeds, turns=turns, alternatives=alternatives,
                          cache=cache_folder() if cache else None,
                          progress=progress)
        if as_json:
            typer.echo(json.dumps(_plain(result), indent=2))
        else:
            _print(result)


class PlanProgress:
    """The plan's progress on standard error, with how long it has taken and an estimate of
    what is left: a live line on a terminal; piped, a line at each new stage and every
    :attr:`every_s` seconds between (a plan takes minutes: it never looks hung)."""

    every_s = 30.0

    def __init__(self, console: Console) -> None:
        self.console = console
        self.what, self.fraction = "starting", 0.0
        self._t0 = time.monotonic()
        self._stop = threading.Event()
        self._status: Status | None = None

    def __call__(self, message: str, fraction: float) -> None:
        """The plan's ``progress`` callback."""
        changed = message != self.what
        self.what, self.fraction = message, float(fraction)
        if self._status is not None:
            self._status.update(self.text())
        elif changed:
            self._say()

    def text(self) -> str:
        """``planning: simulating as designed, seed 1 — 25 %, 40 s so far, about 2 min left``"""
        from calstation import display

        return "planning: " + display.progress_text(self.what, self.fraction,
                                                    time.monotonic() - self._t0)

    def _say(self) -> None:
        self.console.print(self.text(), highlight=False, soft_wrap=True)

    def _beat(self) -> None:
        while not self._stop.wait(self.every_s):
            if self._status is not None:
                self._status.update(self.text())
            else:
                self._say()

    def __enter__(self) -> PlanProgress:
        if self.console.is_terminal:
            self._status = self.console.status(self.text())
            self._status.__enter__()
        else:
            self._say()
        threading.Thread(target=self._beat, daemon=True, name="calstation-plan-progress").start()
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self._stop.set()
        if self._status is not None:
            self._status.__exit__(kind, exc, tb)
        if kind is None:
            from calstation import display

            self.console.print(f"planned in {display.duration(time.monotonic() - self._t0)}",
                               highlight=False)


def _loaded(path: Path, overrides: list[str]) -> LoadedRecipe:
    """The recipe with ``--set`` overrides applied (validated as a recipe)."""
    import yaml

    from calstation.recipes import LoadedRecipe, load_recipe, parse_recipe

    loaded = load_recipe(path)
    if not overrides:
        return loaded
    data = yaml.safe_load(loaded.text)
    for item in overrides:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise typer.BadParameter(f"--set {item!r}: expected KEY=VALUE")
        node = data
        *parents, leaf = key.split(".")
        for part in parents:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise typer.BadParameter(f"--set {item!r}: {part} is not a section")
        node[leaf] = yaml.safe_load(value)
    text = yaml.safe_dump(data, sort_keys=False)
    return LoadedRecipe(parse_recipe(text, f"{path} with --set", path.parent), path, text)


def _plain(value: object) -> JSONValue:
    """The plan as JSON: a number that is not finite is null."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_plain(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    assert isinstance(value, str | int | float | bool) or value is None  # the plan's leaves
    return value


def _print(result: Plan) -> None:
    from rich.console import Console
    from rich.table import Table

    from calstation import display

    console = Console()
    volume = result["work_volume"]
    console.print(
        f"[bold]plan[/] of {result['recipe']} ({result['strategy']}): budget "
        f"{display.number('predicted_error', result['budget_m'])} at "
        f"{display.percent(result['level'], 0)} over r "
        f"{display.number('distance', volume['radius_m'])} × h "
        f"{display.number('distance', volume['height_m'])}; {result['seeds']} simulated "
        f"stations, {display.duration(result['seconds'])}", highlight=False)
    for design in result["designs"]:
        if design.get("error"):
            console.print(f"{design['name']} ({design['change']}): not possible with this "
                          f"fixture: {design['error']}", highlight=False)
            continue
        table = Table(title=f"{design['name']}: {design['change']}")
        for col in ("turns", "σ tx (mm)", "σ tz (mm)", "σ ry (°)", "σ rz (°)",
                    "predicted (mm)", "with the cube (mm)"):
            table.add_column(col, justify="right")
        for row in design["by_turns"]:
            s = row["sigma"]
            table.add_row(str(row["turns"]), *(display.number(p, s[p], unit=False)
                                               for p in ("tx", "tz", "ry", "rz")),
                          display.number("predicted_error", row["predicted_error_m"], unit=False),
                          display.number("predicted_error", row["with_cube_m"], unit=False))
        console.print(table)
        _print_range(console, design["by_turns"], result["axis_sigma_limit_m"])
        need = design["turns_needed"]
        console.print(f"  turns the budget needs: {'—' if need is None else need}")
    for line in result["recommendations"]:
        console.print(f"[green]→[/] {line}", highlight=False)


def _print_range(console: Console, rows: list[ByTurns], axis_limit: float | None) -> None:
    """The σ of the lidar's range terms (from the QA cube's scan) per number of turns, or why
    the recipe cannot measure them; and the σ of where the axis lies, which the cube scan turns
    on for when it is above ``axis_limit`` (``calibration.accuracy.axis_sigma``)."""
    for row in rows:
        sigma = row.get("range_sigma") or {}
        if row.get("range_problem"):
            console.print(f"  [red]lidar range model not measured[/] ({row['turns']} turns): "
                          f"{row['range_problem']}", highlight=False)
        elif sigma:
            parts = [f"σ {name.replace('_', ' ')} "
                     + (f"{_ppm(v)} ppm" if name == "range_scale" else f"{_mm(v)} mm")
                     for name, v in sigma.items()]
            axis = row.get("axis_sigma_m", math.nan)
            if math.isfinite(axis):
                parts.append(f"σ axis position {_mm(axis)} mm"
                             + ("" if axis_limit is None or axis <= axis_limit else
                                f" (above {_mm(axis_limit)} mm: the cube scan turns on, "
                                "calibration.accuracy.axis_sigma)"))
            console.print(f"  lidar range model from the QA cube ({row['turns']} turns of the "
                          f"spin scan): {', '.join(parts)}", highlight=False)


def _ppm(v: float | None) -> str:
    return "—" if v is None or not math.isfinite(v) else f"{v * 1e6:.0f}"


def _mm(v: float | None) -> str:
    return "—" if v is None or not math.isfinite(v) else f"{v * 1e3:.3f}"

