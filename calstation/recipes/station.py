"""The station section of a recipe: the station's identity and its three drivers."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from calstation.recipes.base import Model


class DriverConfig(Model):
    """A driver by its registered name, with the settings its factory validates."""

    driver: str = Field(min_length=1)
    settings: dict[str, object] = Field(default_factory=dict)


class EncoderConfig(DriverConfig):
    """The encoder driver plus the station-level encoder configuration."""

    ppr: int = Field(
        1024, ge=100, le=1_000_000,
        description="pulses per revolution; counts = 4·ppr (at least 400 counts, 0.9°, per turn)",
    )
    direction: Literal[1, -1] = 1
    latency_s: float = Field(
        0.0, ge=-1.0, le=1.0, description="encoder time minus lidar time, compensated"
    )
    accuracy_deg: float = Field(
        0.0, ge=0.0, le=1.0,
        description="the encoder's stated accuracy: the largest error of the angle it reads "
        "over a turn (its datasheet, or the rotary stage's certificate); carried in the σ of "
        "every calibration that combines the spin target with the QA cube",
    )


class StationConfig(Model):
    """The station: its identity and its three drivers.

    ``id`` names the station in the database and in folder names: letters, digits, ``.``, ``_``,
    ``-``.
    """

    id: str = Field(min_length=1, max_length=100, pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
    lidar: DriverConfig
    turntable: DriverConfig
    encoder: EncoderConfig

