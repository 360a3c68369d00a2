"""A whole recipe (:class:`Recipe`), and a validated one with where it came from
(:class:`LoadedRecipe`)."""

from __future__ import annotations

import hashlib
from pathlib import Path

from pydantic import Field

from calstation.engine.settings import QALimits
from calstation.recipes.base import Model
from calstation.recipes.calibration import CalibrationSettings
from calstation.recipes.fixtures import Fixtures
from calstation.recipes.simulation import SimulationConfig
from calstation.recipes.station import StationConfig
from calstation.recipes.steps import Steps


class Recipe(Model):
    """A whole recipe."""

    name: str = Field(min_length=1, max_length=200)
    description: str = Field("", max_length=10_000)
    version: int = Field(1, ge=1, le=1_000_000)
    station: StationConfig
    fixtures: Fixtures = Fixtures()
    simulation: SimulationConfig | None = None
    steps: Steps = Steps()
    calibration: CalibrationSettings = CalibrationSettings()
    qa: QALimits = QALimits()


class LoadedRecipe:
    """A validated recipe with where it came from: path, text and its sha256.

    A recording stores the recipe it was taken with through ``name``, ``text`` and ``sha256``
    (:class:`calstation.recordings.metadata.RecipeInfo`).
    """

    def __init__(self, recipe: Recipe, path: Path | None, text: str) -> None:
        self.recipe = recipe
        self.path = path
        self.text = text
        self.sha256 = hashlib.sha256(text.encode("utf-8")).hexdigest()

    @property
    def name(self) -> str:
        """The recipe's name (``recipe.name``)."""
        return self.recipe.name

    def resolve(self, relative: str) -> Path:
        """A path named in the recipe, relative to the recipe's folder."""
        p = Path(relative)
        if p.is_absolute() or self.path is None:
            return p
        return self.path.parent / p
