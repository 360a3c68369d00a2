"""The calibration section of a recipe: which fine-tuning strategy runs, where it starts, each
stage's settings, and the options of the built-in strategies.

The stage settings are the engine's (:mod:`calstation.engine.settings`). A plugin strategy's
options are checked against the ``options_model`` it declares, in the plugin layer
(:mod:`calstation.plugins.recipe_checks`); the built-ins' options are checked here, with the
recipe itself.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field, ValidationError

from calstation.engine.settings import (
    AccuracySettings,
    InitialSettings,
    PeriodicitySettings,
    ShapeOptions,
    ShapeSettings,
    SigmaLimits,
)
from calstation.recipes.base import Model
from calstation.recipes.problems import Problem, error_message


class RangeOffsetCertificate(Model):
    """``calibration.range_offset_certificate``: the lidar's range offset as measured on a range
    bench (its calibration certificate, or the plant's own characterisation), combined with the
    station's measurement of it (:mod:`calstation.engine.certificate`)."""

    offset: float = Field(
        ..., ge=-0.5, le=0.5,
        description="the lidar's range offset, metres (> 0: it reads long; DESIGN §9)",
    )
    sigma: float = Field(
        ..., gt=0.0, le=0.1,
        description="its uncertainty as a standard deviation, metres (a certificate's expanded "
        "uncertainty at k = 2 is twice this)",
    )


class CalibrationSettings(Model):
    """Which fine-tuning strategy to run, where it starts, and each stage's settings."""

    strategy: str = "periodicity"
    start: Literal["l_target", "platter"] = Field(
        "l_target",
        description="where the fine-tuning starts: the L-target's static scan (the paper), or "
        "the platter's chord in the spin scan itself (no L-target, no static scan)",
    )
    range_model: Literal["none", "offset", "offset+scale"] = Field(
        "offset",
        description="the lidar's range terms estimated with H (DESIGN §9): none, its range "
        "offset (every real lidar has one), or its offset and scale error (the scale needs "
        "the QA cube's known size)",
    )
    incidence_bias: Literal["estimate", "none"] = Field(
        "estimate",
        description="with a range model, estimate the lidar's bias that grows with the angle "
        "between its rays and the surface, c·(1/cos θ − 1), where the fits know the surfaces "
        "(docs/algorithms.md)",
    )
    range_scale_sigma: float = Field(
        1e-4, ge=0.0, le=0.01,
        description="with range_model: offset, the lidar's range scale error it does not "
        "measure, as a standard deviation (dimensionless; 1e-4 is 100 ppm, a time-of-flight "
        "lidar's clock with margin): H's σ and the predicted error carry it (a scale error "
        "moves where the lidar seems to stand by that fraction of its distance). 0 for a "
        "lidar whose scale is known exactly",
    )
    range_offset_certificate: RangeOffsetCertificate | None = Field(
        None,
        description="with a range model, the lidar's range offset from its calibration "
        "certificate: combined with the offset the station measures, it narrows H's σ along "
        "the lidar's boresight; a certificate that disagrees with the measurement beyond "
        "chance refuses the run",
    )
    initial: InitialSettings = InitialSettings()
    shape: ShapeSettings = ShapeSettings()
    periodicity: PeriodicitySettings = PeriodicitySettings()
    accuracy: AccuracySettings = AccuracySettings()
    max_sigma: SigmaLimits = SigmaLimits()
    options: dict[str, dict[str, object]] = Field(
        default_factory=dict, description="settings of plugin strategies, by strategy name"
    )


class PeriodicityOptions(Model):
    """``calibration.options.periodicity``: the built-in periodicity strategy takes its settings
    from ``calibration.periodicity``; no options."""


BUILTIN_OPTIONS: dict[str, type[BaseModel]] = {
    "shape": ShapeOptions,
    "periodicity": PeriodicityOptions,
}
"""The options models of the built-in strategies (plugins declare theirs as the strategy's
``options_model``; see :func:`options_problems`)."""


def options_problems(name: str, model: type[BaseModel], options: object) -> list[Problem]:
    """Problems of ``calibration.options.<name>`` against the strategy's options ``model``."""
    try:
        model.model_validate(options if options is not None else {})
    except ValidationError as exc:
        return [(("calibration", "options", name, *err["loc"]), error_message(err))
                for err in exc.errors()]
    return []

