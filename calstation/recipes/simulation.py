"""The simulation section of a recipe: everything the simulated station models (DESIGN §6).

The checks that relate it to other sections (the range window holds the platter, the spin
target's facets are flatter than the pitch, …) are in :mod:`calstation.recipes.validation`.
"""

from __future__ import annotations

from typing import Annotated, Literal

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


class RangeErrors(Model):
    """The lidar's systematic range errors (DESIGN §9):
    ρ_meas = (1 + scale)·ρ + offset + β(θ) + noise, with β(θ) = incidence_bias·(1/cos θ − 1),
    θ the angle between the ray and the surface's normal (so ``incidence_bias`` is the bias at
    60°: 1/cos 60° − 1 = 1)."""

    offset: float = Field(0.0, ge=-0.5, le=0.5, description="range offset b (m)")
    scale: float = Field(0.0, ge=-0.05, le=0.05, description="range scale error k (1e-3: 0.1 %)")
    incidence_bias: float = Field(
        0.0, ge=-0.05, le=0.05, description="bias at 60° incidence (m), growing as 1/cos θ − 1"
    )


SURFACES = ("platter", "static_target", "spin_target", "qa_cube", "demo", "background")
"""The surfaces whose reflectivity the simulated lidar knows."""


class Reflectivity(Model):
    """Each surface's reflectivity (0–1) and the range bias it causes: a surface of
    reflectivity R reads ``bias·(0.9 − R)/0.8`` longer than true (a 10 % surface ``bias``
    longer than a 90 % one, a 90 % surface unbiased)."""

    bias: float = Field(0.0, ge=-0.05, le=0.05, description="a 10 % surface's bias (m)")
    platter: float = Field(0.9, ge=0.01, le=1.0)
    static_target: float = Field(0.9, ge=0.01, le=1.0)
    spin_target: float = Field(0.9, ge=0.01, le=1.0)
    qa_cube: float = Field(0.9, ge=0.01, le=1.0)
    demo: float = Field(0.9, ge=0.01, le=1.0)
    background: float = Field(0.9, ge=0.01, le=1.0)

    def range_bias(self, surface: str) -> float:
        """The range bias (m) of ``surface`` (one of :data:`SURFACES`)."""
        return float(self.bias * (0.9 - getattr(self, surface)) / 0.8)


class Warmup(Model):
    """A slow range drift while the lidar warms up: ``drift·(1 − exp(−t/time_constant_s))``
    added to every range, t the time since the lidar was switched on (``on_before_s`` before
    the station started)."""

    drift: float = Field(0.0, ge=-0.05, le=0.05, description="drift when warm (m)")
    time_constant_s: float = Field(900.0, gt=0, le=1.0e6)
    on_before_s: float = Field(0.0, ge=0, le=1.0e7)


class EncoderErrors(Model):
    """The encoder's angle errors: the reported angle is φ + e₁·sin(φ + p₁) + e₂·sin(2φ + p₂)
    (an eccentric code disc, once per turn, and its second harmonic)."""

    eccentricity_deg: float = Field(0.0, ge=0, le=5)
    eccentricity_phase_deg: float = Field(0.0, ge=-360, le=360)
    second_harmonic_deg: float = Field(0.0, ge=0, le=5)
    second_harmonic_phase_deg: float = Field(0.0, ge=-360, le=360)


class AxisErrors(Model):
    """The turntable's axis wobble: the platter's axis precesses once per turn, tilted by
    ``wobble_deg`` toward a direction that turns with the platter (``wobble_phase_deg`` from
    +Y_D) — the same as a platter (and what stands on it) tilted by ``wobble_deg`` on a perfect
    axis."""

    wobble_deg: float = Field(0.0, ge=0, le=2)
    wobble_phase_deg: float = Field(0.0, ge=-360, le=360)


class PlatterErrors(Model):
    """A platter top that is not quite flat: a shallow dish of ``flatness`` peak to valley
    (m; positive: the rim higher than the centre), its mean plane at the nominal top."""

    flatness: float = Field(0.0, ge=-0.005, le=0.005)


class SensorModel(Model):
    """What a real station has and the ideal simulator does not: the lidar's systematic range
    errors, reflectivity, mixed pixels from the beam's footprint, the warm-up drift, the
    encoder's and the axis's errors, a platter that is not quite flat. Every item defaults to
    none; ``recipes/sim-realistic.yaml`` sets datasheet-level values."""

    range: RangeErrors = RangeErrors()
    reflectivity: Reflectivity = Reflectivity()
    mixed_pixels: Literal["random", "footprint"] = Field(
        "random",
        description="random: a random blend of the two sub-beams at a depth edge "
        "(lidar.mixed_pixel_prob); footprint: the mean over the beam's footprint",
    )
    warmup: Warmup = Warmup()
    encoder: EncoderErrors = EncoderErrors()
    axis: AxisErrors = AxisErrors()
    platter: PlatterErrors = PlatterErrors()


class SimulationConfig(Model):
    """Everything the simulated station models. Seeded and deterministic."""

    seed: int = Field(0, ge=0, le=2**63 - 1)
    truth: TruthConfig = TruthConfig()
    lidar: LidarModel = LidarModel()
    turntable: TurntableModel = TurntableModel()
    encoder: EncoderModel = EncoderModel()
    placement: PlacementError = PlacementError()
    background: BackgroundModel = BackgroundModel()
    sensor: SensorModel = SensorModel()

