"""``calstation recipes``: validate recipe files and list the recipes at hand."""

from __future__ import annotations

import os
from pathlib import Path

import typer

from calstation.cli._console import wide_console


def recipe_dirs() -> list[Path]:
    """Folders ``recipes list`` searches (``$CALSTATION_RECIPES``, ./recipes, shipped, home)."""
    from calstation.storage.db import calstation_home

    candidates = [
        Path.cwd() / "recipes",
        Path(__file__).resolve().parents[2] / "recipes",
        calstation_home() / "recipes",
    ]
    extra = os.environ.get("CALSTATION_RECIPES")
    if extra:
        candidates = [Path(p) for p in extra.split(os.pathsep) if p] + candidates
    seen: list[Path] = []
    for c in candidates:
        r = c.resolve()
        if r.is_dir() and r not in seen:
            seen.append(r)
    return seen


def register(app: typer.Typer) -> None:
    """Add the ``recipes`` command group."""
    recipes_app = typer.Typer(help="Validate and list recipes.", no_args_is_help=True)
    app.add_typer(recipes_app, name="recipes")

    @recipes_app.command("validate")
    def validate(
        files: list[Path] = typer.Argument(..., help="Recipe YAML files."),
        plugins: bool = typer.Option(
            True, "--plugins/--no-plugins",
            help="Also check that the drivers and strategy named are installed.",
        ),
    ) -> None:
        """Validate recipe files: every problem with its field and YAML line."""
        from calstation.errors import RecipeError
        from calstation.plugins.recipe_checks import check_plugins
        from calstation.recipes import load_recipe

        failures = []
        for f in files:
            try:
                loaded = load_recipe(f)
                if plugins:
                    check_plugins(loaded)
            except RecipeError as exc:
                failures.append(str(exc))  # every message names its file
                continue
            r = loaded.recipe
            typer.echo(
                f"{f}: OK — recipe {r.name!r}, station {r.station.id}, drivers "
                f"{r.station.lidar.driver}/{r.station.turntable.driver}/"
                f"{r.station.encoder.driver}, strategy {r.calibration.strategy}"
            )
        if failures:
            raise RecipeError("\n".join(failures))

    @recipes_app.command("list")
    def list_recipes(
        folders: list[Path] = typer.Argument(None, help="Folders to search (default: see docs)."),
    ) -> None:
        """List the recipes found, with station, drivers, strategy and validity."""
        from rich.table import Table

        from calstation.errors import RecipeError
        from calstation.recipes import load_recipe

        dirs = [d.resolve() for d in folders] if folders else recipe_dirs()
        table = Table(title="Recipes")
        for col in ("file", "name", "station", "drivers", "strategy", "status"):
            table.add_column(col)
        count = 0
        for d in dirs:
            for f in sorted([*d.glob("*.yaml"), *d.glob("*.yml")]):
                count += 1
                try:
                    r = load_recipe(f).recipe
                except RecipeError as exc:
                    first = str(exc).splitlines()[-1].strip()
                    table.add_row(f.name, "", "", "", "", f"[red]invalid[/]: {first}")
                    continue
                drivers = "/".join(
                    getattr(r.station, k).driver for k in ("lidar", "turntable", "encoder")
                )
                table.add_row(f.name, r.name, r.station.id, drivers, r.calibration.strategy,
                              "[green]ok[/]")
        console = wide_console()
        if count == 0:
            console.print(f"no recipes in {', '.join(map(str, dirs)) or '(no folder)'}")
            return
        console.print(table)
