"""``calstation simulate``: the recordings of a whole run on the simulated station."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer


def simulate(
    recipe: Annotated[Path, typer.Argument(help="recipe YAML (its simulation: section is used)")],
    out: Annotated[Path, typer.Option("--out", help="output folder for the recordings")],
    seed: Annotated[int | None, typer.Option(help="random seed (default: the recipe's)")] = None,
    range_m: Annotated[
        float | None,
        typer.Option("--range", help="lidar-to-platter-centre distance, metres"),
    ] = None,
    pitch_deg: Annotated[
        float | None, typer.Option("--pitch", help="lidar pitch, degrees (rz = −pitch)")
    ] = None,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="no progress bars")] = False,
) -> None:
    """Simulate a run: static.mcap, spin.mcap, cube.mcap and truth.json in --out."""
    from rich.console import Console

    from calstation.recipes import load_recipe

    from .run import simulate_run

    loaded = load_recipe(recipe)
    paths = simulate_run(
        loaded, out, seed=seed, range_m=range_m, pitch_deg=pitch_deg, progress=not quiet
    )
    console = Console()
    for name, path in paths.items():
        console.print(f"{name:>7}: {path}", highlight=False)


def register(app: typer.Typer) -> None:
    """Add ``simulate`` to the ``calstation`` CLI."""
    app.command("simulate")(simulate)
