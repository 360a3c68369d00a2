"""Reading a recipe: :func:`load_recipe` (a file) and :func:`parse_recipe` (text).

Every problem is reported with the YAML field path and line (:mod:`calstation.recipes.problems`):
first the field checks of the models, then the checks that relate fields to each other
(:mod:`calstation.recipes.validation`). The checks against the installed plugins are not run
here; callers that need them call :func:`calstation.plugins.recipe_checks.check_plugins`.
"""

from __future__ import annotations

from pathlib import Path

import yaml
from pydantic import ValidationError

from calstation.errors import RecipeError
from calstation.recipes.problems import (
    MAX_SHOWN,
    error_message,
    format_loc,
    format_problems,
    line_of,
    problems_message,
)
from calstation.recipes.recipe import LoadedRecipe, Recipe
from calstation.recipes.validation import cross_field_problems
from calstation.yamlsafe import YamlProblem, load_yaml, read_text_file

MAX_RECIPE_BYTES = 1_000_000
"""Largest recipe file accepted (bytes)."""

_UNION_TAGS = {
    "l_target",
    "frustum",
    "cube",
    "pyramid",
    "prism",
    "mesh",
}
"""The fixture kinds: pydantic puts the tag of a tagged union in an error's location; the
recipe's field path has no such level."""


def _is_union_tag(key: int | str) -> bool:
    return isinstance(key, str) and key in _UNION_TAGS


def load_recipe(path: str | Path) -> LoadedRecipe:
    """Read and validate a recipe file.

    Only a regular file of at most :data:`MAX_RECIPE_BYTES` is read (a FIFO or a device is
    refused, never opened). Raises :class:`RecipeError` if the file is missing, is not YAML, or
    fails validation; the message names the file, each field and its line.
    """
    p = Path(path)
    try:
        text = read_text_file(p, "recipe", MAX_RECIPE_BYTES)
    except ValueError as exc:
        message = str(exc)
        if message == "recipe not found":
            message = "recipe file not found"
        raise RecipeError(f"{p}: {message}") from None
    return LoadedRecipe(parse_recipe(text, str(p), p.parent), p, text)


def parse_recipe(text: str, source: str = "<recipe>", base_dir: Path | None = None) -> Recipe:
    """Validate recipe YAML text; :class:`RecipeError` names the field and line of each problem.

    The text is bounded first (size, nesting, duplicate keys: :mod:`calstation.yamlsafe`). After
    the field checks, :func:`cross_field_problems` runs the checks that relate fields to each
    other (and mesh files to ``base_dir``, the recipe's folder, when given).
    """
    if len(text) > MAX_RECIPE_BYTES:
        raise RecipeError(
            f"{source}: the recipe is {len(text) / 1e6:.1f} MB, more than the "
            f"{MAX_RECIPE_BYTES / 1e6:g} MB calstation accepts"
        )
    try:
        data, node = load_yaml(text)
    except YamlProblem as exc:
        where = f"{source}:{exc.line}" if exc.line else source
        field = f"{format_loc(exc.loc)}: " if exc.loc else ""
        raise RecipeError(f"invalid recipe:\n  {where}: {field}{exc.message}") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{source}:{mark.line + 1}" if mark is not None else source
        problem = getattr(exc, "problem", None) or str(exc)
        raise RecipeError(f"{where}: not valid YAML: {problem}") from None
    except RecursionError:  # not reached after the depth check; kept as a last guard
        raise RecipeError(f"{source}: the recipe is nested too deeply") from None
    if not isinstance(data, dict):
        raise RecipeError(f"{source}: a recipe must be a YAML mapping, got {type(data).__name__}")
    try:
        recipe = Recipe.model_validate(data)
    except ValidationError as exc:
        problems = []
        for err in exc.errors()[:MAX_SHOWN]:
            loc = tuple(k for k in err["loc"] if not _is_union_tag(k))
            line = line_of(node, loc)
            where = f"{source}:{line}" if line else source
            problems.append(f"{where}: {format_loc(loc)}: {error_message(err)}")
        raise RecipeError(problems_message(problems, exc.error_count())) from None
    cross = cross_field_problems(recipe, base_dir)
    if cross:
        raise RecipeError(format_problems(cross, node, source))
    return recipe
