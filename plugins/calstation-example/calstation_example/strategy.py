"""The example plugin's fine-tuning strategy: shape-constrained fine-tuning with ry held.

A template for a strategy plugin: it declares its fixture (the QA cube) and an options model
(``calibration.options.example-ry-held`` in a recipe, checked by ``calstation recipes validate``
with file and line), reads its options with
:func:`calstation.plugins.cost_strategies.strategy_options`, and re-uses calstation's engine
(:func:`calstation.engine.shape.shape_fine_tune`). calstation checks what it returns (finite, near
its start) and times it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal

from pydantic import BaseModel, ConfigDict, Field

if TYPE_CHECKING:  # the engine loads when the strategy runs, not when it is registered
    from calstation.engine.frames import Extrinsics
    from calstation.engine.result import CalibrationResult
    from calstation.plugins.cost_strategies import Progress
    from calstation.recipes import Recipe
    from calstation.recordings.recorded import Recording


class RyHeldOptions(BaseModel):
    """``calibration.options.example-ry-held``: unknown keys are errors."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    box: Literal["upright", "minimal"] = Field("upright", description="the cube's box model")
    coarse: bool = Field(True, description="coarse alignment of a far start first")


class RyHeldStrategy:
    """Shape-constrained fine-tuning on the QA cube that keeps ry at its start (for stations
    whose ry is known from the mechanics)."""

    name = "example-ry-held"
    fixture = "qa_cube"
    options_model = RyHeldOptions

    def run(
        self,
        recording: Recording,
        start: Extrinsics,
        recipe: Recipe,
        progress: Progress | None = None,
    ) -> CalibrationResult:
        """Refine tx, ty, tz, rz from the cube's spin scan; ry stays at ``start.ry``."""
        from dataclasses import replace

        from calstation.engine.shape import shape_fine_tune
        from calstation.plugins.cost_strategies import strategy_options

        options = strategy_options(self, recipe, RyHeldOptions)
        result = shape_fine_tune(
            recording,
            start,
            recipe.fixtures.qa_cube,
            recipe.calibration.shape,
            platter_radius=recipe.fixtures.platter.radius,
            box=options.box,
            estimate_ry=False,
            coarse=options.coarse,
            progress=progress,
        )
        return replace(result, strategy=self.name)
