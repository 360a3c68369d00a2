"""``calstation recipes``: validate recipe files, list the recipes at hand, and copy one that
calstation ships to start a station's own."""

from __future__ import annotations

import os
from pathlib import Path

import typer

from calstation.cli._console import wide_console


def recipe_dirs() -> list[Path]:
    """Folders ``recipes list`` searches (``$CALSTATION_RECIPES``, ./recipes, the recipes
    calstation ships, ``$CALSTATION_HOME/recipes``)."""
    from calstation.recipes.catalog import SHIPPED_DIR
    from calstation.storage.db import calstation_home

    candidates = [Path.cwd() / "recipes", SHIPPED_DIR, calstation_home() / "recipes"]
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
    recipes_app = typer.Typer(help="Validate, list and copy recipes.", no_args_is_help=True)
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
        from calstation.recipes import SHIPPED_DIR

        table = Table(title="Recipes", caption="a shipped one is copied to start a station's "
                      "own with `calstation recipes copy NAME PATH`")
        for col in ("file", "in", "name", "station", "drivers", "strategy", "status"):
            table.add_column(col)
        count = 0
        for d in dirs:
            where = "shipped" if d == SHIPPED_DIR else str(d)
            for f in sorted([*d.glob("*.yaml"), *d.glob("*.yml")]):
                count += 1
                try:
                    r = load_recipe(f).recipe
                except RecipeError as exc:
                    first = str(exc).splitlines()[-1].strip()
                    table.add_row(f.name, where, "", "", "", "", f"[red]invalid[/]: {first}")
                    continue
                drivers = "/".join(
                    getattr(r.station, k).driver for k in ("lidar", "turntable", "encoder")
                )
                table.add_row(f.name, where, r.name, r.station.id, drivers,
                              r.calibration.strategy, "[green]ok[/]")
        console = wide_console()
        if count == 0:
            console.print(f"no recipes in {', '.join(map(str, dirs)) or '(no folder)'}")
            return
        console.print(table)

    @recipes_app.command("copy")
    def copy(
        name: str = typer.Argument(..., help="A shipped recipe (see `recipes list`)."),
        path: Path = typer.Argument(..., help="The file to write, or a folder for NAME.yaml."),
        force: bool = typer.Option(False, "--force", help="Replace PATH when it is a file."),
    ) -> None:
        """Copy a recipe calstation ships to PATH, to start a station's own from it."""
        from calstation.recipes import shipped_recipe

        source = shipped_recipe(name)
        target = copy_recipe(source, path, force=force)
        typer.echo(f"{source.name} copied to {target}; edit it, then check it with "
                   f"`calstation recipes validate {target}`")


def copy_recipe(source: Path, path: Path, *, force: bool = False) -> Path:
    """Write ``source``'s text to ``path`` (a folder: ``path/<source's name>``), in one step: a
    reader sees the old file or the whole new one. An existing file is replaced only when it was
    named and ``force`` is given; :class:`~calstation.errors.RecipeError` otherwise, and when the
    folder is missing; :class:`~calstation.errors.OutputError` when the write fails (the file
    there is then as it was)."""
    from calstation.atomic import write_atomic
    from calstation.errors import RecipeError

    named = not path.is_dir()
    target = path if named else path / source.name
    if target.exists() and not (force and named and target.is_file()):
        raise RecipeError(f"{target} exists; " + (
            "give --force to replace it" if named and target.is_file()
            else "name the file to write (a file already there is replaced only when named)"))
    if not target.parent.is_dir():
        raise RecipeError(f"cannot copy the recipe to {target}: the folder {target.parent} "
                          "does not exist")
    return write_atomic(target, source.read_bytes(), "recipe")
