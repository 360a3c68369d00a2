"""The recipes calstation ships: YAML files carried in the package (``calstation/recipes/shipped/``;
a checkout's ``recipes/`` links to them), so an installed calstation lists and copies them
(``calstation recipes list``, ``calstation recipes copy NAME PATH``) without its checkout."""

from __future__ import annotations

from pathlib import Path

from calstation.errors import RecipeError

SHIPPED_DIR = Path(__file__).resolve().parent / "shipped"
"""The folder of the shipped recipes, in the installed package."""


def shipped_recipes() -> list[Path]:
    """The shipped recipes' files, by name."""
    return sorted(SHIPPED_DIR.glob("*.yaml"))


def shipped_recipe(name: str) -> Path:
    """The shipped recipe ``name`` (its file name, with or without ``.yaml``);
    :class:`RecipeError` naming the shipped ones when there is none by that name."""
    stem = name.removesuffix(".yaml").removesuffix(".yml")
    found = {p.stem: p for p in shipped_recipes()}
    if stem not in found or "/" in name or "\\" in name:
        raise RecipeError(
            f"no shipped recipe named {name!r}; calstation ships: {', '.join(found) or 'none'}"
        )
    return found[stem]
