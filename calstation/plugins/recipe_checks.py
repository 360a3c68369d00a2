"""The checks of a recipe against the installed plugins.

A recipe names its drivers and its fine-tuning strategy; whether they are installed, and whether
the driver ``settings`` and strategy ``calibration.options`` fit the models the plugins declare,
is known only here, above the recipes (:mod:`calstation.recipes` knows no plugin).
:func:`calstation.recipes.load_recipe` does not run these checks: ``calstation recipes
validate`` (unless ``--no-plugins``) and the station, before a run starts or resumes, call
:func:`check_plugins`.
"""

from __future__ import annotations

import importlib
from typing import Protocol, runtime_checkable

from pydantic import BaseModel, ValidationError

from calstation import plugins
from calstation.errors import PluginError, RecipeError
from calstation.plugins.cost_strategies import recipe_option_problems
from calstation.recipes.problems import Problem, error_message, format_problems
from calstation.recipes.recipe import LoadedRecipe, Recipe
from calstation.yamlsafe import load_yaml


@runtime_checkable
class DeclaresSettings(Protocol):
    """A driver factory that declares ``settings_model``: the pydantic model of its settings,
    or that model's import path ``"package.module:Class"``."""

    settings_model: type[BaseModel] | str


def settings_model_of(factory: object) -> type[BaseModel] | None:
    """The pydantic model a driver factory declares for its ``settings`` (None if none): its
    ``settings_model``, given as the class or, so that registering costs no import, as the
    class's import path ``"package.module:Class"`` (imported here, when a recipe is checked).
    :class:`PluginError` when it cannot be imported or is not a pydantic model class."""
    if not isinstance(factory, DeclaresSettings):
        return None
    model: object = factory.settings_model
    if isinstance(model, str):
        module, _, name = model.partition(":")
        try:
            model = getattr(importlib.import_module(module), name)
        except (ImportError, AttributeError) as exc:
            raise PluginError(
                f"the driver factory {factory!r} declares settings_model {model!r}, which cannot "
                f"be imported: {exc}"
            ) from exc
    if model is None:
        return None
    if not (isinstance(model, type) and issubclass(model, BaseModel)):
        raise PluginError(
            f"the driver factory {factory!r} declares settings_model {model!r}, which is not a "
            "pydantic model class"
        )
    return model


def plugin_problems(recipe: Recipe) -> list[Problem]:
    """Checks against the installed plugins: drivers and strategies named must be registered,
    each driver's ``settings`` must fit the ``settings_model`` its factory declares, and each
    strategy's options the ``options_model`` it declares."""
    return _driver_problems(recipe) + _strategy_problems(recipe)


def check_plugins(loaded: LoadedRecipe) -> None:
    """Raise :class:`RecipeError` (field and line of each problem) if a driver or strategy the
    recipe names is not installed, or a strategy's options do not fit its options model."""
    problems = plugin_problems(loaded.recipe)
    if problems:
        source = str(loaded.path) if loaded.path is not None else "<recipe>"
        _, node = load_yaml(loaded.text)
        raise RecipeError(format_problems(problems, node, source))


def _driver_problems(recipe: Recipe) -> list[Problem]:
    """Each driver is registered under its name, and its settings fit its settings model."""
    problems: list[Problem] = []
    registered = plugins.drivers()
    for kind in plugins.DRIVER_KINDS:
        config = getattr(recipe.station, kind)
        name = config.driver
        settings_model = settings_model_of(registered[(kind, name)].factory) if (
            kind, name) in registered else None
        if settings_model is not None:
            try:
                settings_model.model_validate(config.settings)
            except ValidationError as exc:
                problems += [(("station", kind, "settings", *err["loc"]), error_message(err))
                             for err in exc.errors()]
        if (kind, name) not in registered:
            known = sorted(n for (k, n) in registered if k == kind)
            problems.append(
                (
                    ("station", kind, "driver"),
                    f"no {kind} driver named {name!r} is installed; "
                    f"installed: {', '.join(known) or 'none'}",
                )
            )
    return problems


def _strategy_problems(recipe: Recipe) -> list[Problem]:
    """The strategy and every ``calibration.options`` key name registered strategies, and each
    strategy's options fit its options model."""
    problems: list[Problem] = []
    strategies = plugins.strategies()
    if recipe.calibration.strategy not in strategies:
        problems.append(
            (
                ("calibration", "strategy"),
                f"no fine-tuning strategy named {recipe.calibration.strategy!r} is installed; "
                f"installed: {', '.join(sorted(strategies)) or 'none'}",
            )
        )
    for name in recipe.calibration.options:
        if name not in strategies:
            problems.append(
                (("calibration", "options", name), f"options for unknown strategy {name!r}")
            )
    problems += recipe_option_problems(recipe, strategies)
    return problems
