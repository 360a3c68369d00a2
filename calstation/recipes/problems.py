"""Recipe problems: a field path and what is wrong, worded and located for the user.

Every check of a recipe, in this package and in the plugin layer
(:mod:`calstation.plugins.recipe_checks`), returns :data:`Problem` values; the loader reports them
with :func:`format_problems`, each as ``file:line: field.path: message``.
"""

from __future__ import annotations

import yaml
from pydantic_core import ErrorDetails

Problem = tuple[tuple[int | str, ...], str]
"""A validation problem: the field path in the recipe and what is wrong."""

MAX_SHOWN = 20
"""Problems listed in one error; the rest are counted (a file of thousands of unknown keys is
refused at once, not after locating each)."""


def line_of(node: yaml.Node | None, loc: tuple[int | str, ...]) -> int | None:
    """1-based line of the YAML node at ``loc`` (the deepest one that exists)."""
    line = None if node is None else node.start_mark.line + 1
    for key in loc:
        if isinstance(node, yaml.MappingNode):
            for k, v in node.value:
                if k.value == key:
                    line = k.start_mark.line + 1
                    node = v
                    break
            else:
                return line
        elif isinstance(node, yaml.SequenceNode) and isinstance(key, int):
            if key >= len(node.value):
                return line
            node = node.value[key]
            line = node.start_mark.line + 1
        else:
            return line
    return line


def format_loc(loc: tuple[int | str, ...]) -> str:
    """A field path as the recipe's user writes it: ``fixtures.demo[0].edge``."""
    parts: list[str] = []
    for key in loc:
        if isinstance(key, int):
            parts.append(f"[{key}]")
        else:
            parts.append(("." if parts else "") + str(key))
    return "".join(parts) or "(top level)"


def error_message(err: ErrorDetails) -> str:
    """A pydantic error in the recipe's words (the value it got included where it helps)."""
    if err["type"] == "extra_forbidden":
        return "unknown key"
    msg = str(err["msg"])
    if err["type"] in ("finite_number", "float_parsing", "int_parsing", "int_from_float"):
        return f"{msg} (got {err.get('input')!r})"
    if err["type"] in ("greater_than", "greater_than_equal", "less_than", "less_than_equal"):
        return f"{msg} (got {err.get('input')!r})"
    return msg


def format_problems(problems: list[Problem], node: yaml.Node | None, source: str) -> str:
    """The message of a :class:`~calstation.errors.RecipeError` listing ``problems``, each with
    ``source`` (the file) and the line of its field in the YAML tree ``node``."""
    lines = []
    for loc, msg in problems[:MAX_SHOWN]:
        line = line_of(node, loc)
        where = f"{source}:{line}" if line else source
        lines.append(f"{where}: {format_loc(loc)}: {msg}")
    return problems_message(lines, len(problems))


def problems_message(lines: list[str], total: int) -> str:
    """``invalid recipe:`` and the located problems ``lines`` (the first of ``total``)."""
    more = total - len(lines)
    tail = [f"… and {more} more problem{'s' if more > 1 else ''}"] if more > 0 else []
    return "invalid recipe:\n  " + "\n  ".join([*lines, *tail])
