"""The simulation section of a recipe: everything the simulated station models (DESIGN §6).

The checks that relate it to other sections (the range window holds the platter, the spin
target's facets are flatter than the pitch, …) are in :mod:`calstation.recipes.validation`.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import Field, model_validator

from calstation.recipes.base import Model


class TruthConfig(Model):
    """The true lidar pose of the simulated station.

    Either ``range``/``pitch_deg`` plus small deviations (the paper's scenarios: the boresight
    hits the platter centre at ``range`` metres, looking down at ``pitch_deg``), or the explicit
    extrinsics ``H`` (tx, ty, tz m; rx, ry, rz rad). Deviations not given are drawn from the seed
    within the ``*_max`` bounds.
    """

    range: float = Field(1.25, ge=0.2, le=20.0)
    pitch_deg: float = Field(45.0, gt=5, lt=85)
    tx_max: float = Field(0.020, ge=0, le=0.5)
    tz_max: float = Field(0.015, ge=0, le=0.5)
    ry_max_deg: float = Field(0.5, ge=0, le=10)
    rz_max_deg: float = Field(0.5, ge=0, le=10)
    H: dict[str, Annotated[float, Field(ge=-20.0, le=20.0)]] | None = Field(
        None, description="tx, ty, tz (m, within ±20) and rx, ry, rz (rad, within ±π)"
    )


class LidarModel(Model):
    """The simulated line scanner."""

    fov_deg: float = Field(72.0, ge=1, le=360)
    points_per_line: int = Field(1000, ge=2, le=100_000)
    line_rate_hz: float = Field(1000.0, ge=1, le=100_000)
    range_noise: float = Field(0.001, ge=0, le=0.1)
    range_min: float = Field(0.2, ge=0, le=100)
    range_max: float = Field(10.0, ge=0.1, le=200)
    dropout: float = Field(0.002, ge=0, le=0.9)
    mixed_pixel_prob: float = Field(0.5, ge=0, le=1)
    beam_divergence_deg: float = Field(0.03, ge=0, le=5)
    max_points_per_second: float = Field(1.0e6, ge=1, le=1.0e8)

    @model_validator(mode="after")
    def _rate(self) -> LidarModel:
        if self.points_per_line * self.line_rate_hz > self.max_points_per_second * (1 + 1e-9):
            raise ValueError(
                f"points_per_line × line_rate_hz = {self.points_per_line * self.line_rate_hz:g} "
                f"points/s exceeds the {self.max_points_per_second:g} points/s of this lidar"
            )
        return self


class TurntableModel(Model):
    """The simulated turntable drive."""

    acceleration_rpm_s: float = Field(60.0, ge=0.1, le=10_000)
    speed_ripple: float = Field(0.005, ge=0, le=0.3, description="relative speed ripple")
    ripple_per_rev: int = Field(3, ge=0, le=100)


class EncoderModel(Model):
    """The simulated encoder's non-idealities (ppr/direction come from the station config)."""

    sample_rate_hz: float = Field(1000.0, ge=10, le=1.0e6)
    latency_s: float = Field(0.0, ge=-1.0, le=1.0)


class PlacementError(Model):
    """How far the operator misplaces fixtures (1σ)."""

    position_sigma: float = Field(0.002, ge=0, le=0.05)
    yaw_sigma_deg: float = Field(0.5, ge=0, le=10)


class BackgroundModel(Model):
    """Static scenery around the turntable, in frame P."""

    floor_depth: float = Field(
        0.8, ge=0.01, le=100, description="floor plane this far below the platter top"
    )
    wall_distance: float = Field(
        2.5, ge=0.1, le=100, description="back wall this far from the axis"
    )
    enabled: bool = True


class SimulationConfig(Model):
    """Everything the simulated station models. Seeded and deterministic."""

    seed: int = Field(0, ge=0, le=2**63 - 1)
    truth: TruthConfig = TruthConfig()
    lidar: LidarModel = LidarModel()
    turntable: TurntableModel = TurntableModel()
    encoder: EncoderModel = EncoderModel()
    placement: PlacementError = PlacementError()
    background: BackgroundModel = BackgroundModel()

