"""The engine's settings: what each algorithm takes besides its arrays.

Each is a small immutable pydantic model with the paper's defaults (DESIGN §5), so that a caller
without a recipe (a notebook, a port, a test) gets them by constructing the model. A recipe
nests the same models (``calibration.periodicity`` *is* a :class:`PeriodicitySettings`), so a
recipe's section is handed to the engine as it is; the recipes layer adds the station, the
drivers, the steps and the checks that span sections. Lengths are metres; angles carry their
unit in the field name.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

Coordinate = Annotated[float, Field(ge=-1.5, le=1.5)]
"""A position on the platter (m); whether the fixture fits is checked against the platter."""
Yaw = Annotated[float, Field(ge=-360, le=360)]

class Settings(BaseModel):
    """Base of the engine's settings (and of every recipe model, which nests them): unknown keys
    are errors, values are immutable, numbers finite."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class PlatterGeometry(Settings):
    """The turntable's platter: a disk whose top surface is the P frame's origin plane."""

    diameter: float = Field(0.585, ge=0.05, le=3.0)
    thickness: float = Field(0.010, ge=0.001, le=0.2)

    @property
    def radius(self) -> float:
        """Half the diameter, metres."""
        return 0.5 * self.diameter


DEFAULT_PLATTER_RADIUS = PlatterGeometry().radius
"""The default platter's radius (m), for library functions called without a recipe; the
station, the CLI and the bench always pass the recipe's ``platter.radius``."""


class LTargetGeometry(Settings):
    """The static L-shaped target of the initial calibration (paper §III-A).

    Base plate along Y_P from A (front, toward the lidar) to the back wall at B; the wall rises
    along X_P; ``width`` runs along Z_P; wall height above the base top is ``h_tall`` at
    z_P = −width/2 and ``h_short`` at +width/2 (linear, ``h_mid`` at the centre).
    """

    kind: Literal["l_target"] = "l_target"
    base_length: float = Field(0.15, ge=0.01, le=1.5)
    base_thickness: float = Field(0.010, ge=0.001, le=0.1)
    wall_thickness: float = Field(0.010, ge=0.001, le=0.1)
    width: float = Field(0.20, ge=0.01, le=1.5)
    h_tall: float = Field(0.15, ge=0.002, le=1.0)
    h_mid: float = Field(0.10, ge=0.002, le=1.0)
    h_short: float = Field(0.05, ge=0.001, le=1.0)
    offset: tuple[Coordinate, Coordinate] = Field(
        (0.0, 0.0), description="(y_P, z_P) of B relative to the platter centre, metres"
    )
    mesh: str | None = Field(None, description="optional CAD mesh (STL/PLY/OBJ) in frame D")

    @model_validator(mode="after")
    def _heights(self) -> LTargetGeometry:
        if not self.h_tall > self.h_short:
            raise ValueError("h_tall must be greater than h_short")
        if not self.h_short < self.h_mid < self.h_tall:
            raise ValueError("h_mid must lie between h_short and h_tall")
        if not math.isclose(self.h_mid, 0.5 * (self.h_tall + self.h_short), rel_tol=0.02):
            raise ValueError("h_mid must be the mean of h_tall and h_short (linear wall top)")
        return self


class CubeGeometry(Settings):
    """A cube of edge ``edge`` standing on the platter (the QA cube)."""

    kind: Literal["cube"] = "cube"
    edge: float = Field(0.100, ge=0.01, le=1.0)
    edge_tolerance: float = Field(
        0.00005,
        ge=0.0,
        le=0.01,
        description="± how well the edge is known, metres (the cube's certificate): the shape "
        "strategy's known-size fit carries it in its σ",
    )
    same_finish_as_platter: bool = Field(
        False,
        description="the cube and the platter's top are of one material and finish, so that "
        "the lidar reads their ranges alike (a reflectivity difference moves a lidar's ranges "
        "by up to millimetres): the cube's height above the platter is then a known length, "
        "which calibration.range_model: offset+scale needs to measure the range scale error",
    )
    offset: tuple[Coordinate, Coordinate] = (0.08, 0.05)
    yaw_deg: Yaw = 20.0
    mesh: str | None = None


class InitialSettings(Settings):
    """Initial calibration (paper §IV-A)."""

    bin_deg: float = Field(0.02, ge=0.001, le=1.0)
    line_tolerance: float = Field(
        0.002, ge=1e-5, le=0.1, description="max RMS of a line segment, metres"
    )
    min_segment_points: int = Field(8, ge=3, le=10_000)
    angle_tolerance_deg: float = Field(10.0, ge=0.1, le=45)
    length_tolerance: float = Field(
        0.3, ge=0.01, le=1.0, description="relative tolerance on CAD lengths"
    )


class OptimizerSettings(Settings):
    """SciPy least_squares (TRF) settings shared by the fine-tuning strategies."""

    translation_bound: float = Field(0.020, ge=1e-4, le=1.0)
    rotation_bound_deg: float = Field(2.0, ge=0.01, le=30)
    xtol: float = Field(1e-12, ge=1e-15, le=1.0)
    ftol: float = Field(1e-10, ge=1e-15, le=1.0)


class ShapeSettings(OptimizerSettings):
    """Shape-constrained fine-tuning (paper §III-B-1, §IV-B)."""

    max_nfev: int = Field(100, ge=1, le=1000)
    segment_margin: float = Field(0.010, ge=0, le=0.1)
    outlier_radius: float = Field(0.001, ge=1e-5, le=0.1)
    outlier_neighbours: int = Field(8, ge=0, le=100)


class PeriodicitySettings(OptimizerSettings):
    """Periodicity-constrained fine-tuning (paper §III-B-2, §IV-C) and its robustness schedule."""

    max_nfev: int = Field(10, ge=1, le=100, description="evaluations per inner solve")
    max_outer: int = Field(15, ge=1, le=50)
    match_distance: float = Field(0.20, ge=0.001, le=2.0)
    normal_neighbours: int = Field(50, ge=3, le=200)
    coarse_to_fine: bool = True
    gauge: Literal["platter", "ty"] = "platter"
    ry_bound_deg: float = Field(
        2.5,
        ge=0.01,
        le=30,
        description="ry bound around its start (never re-centred): set-B starts are 2° off",
    )


class ShapeOptions(Settings):
    """``calibration.options.shape``: the built-in shape strategy's choices (docs/algorithms.md)."""

    box: Literal["upright", "minimal"] = Field(
        "upright",
        description="upright: calstation's box standing on the platter; minimal: the paper's",
    )
    estimate_ry: bool = Field(True, description="estimate ry (false: hold it at its start)")
    coarse: bool = Field(True, description="coarse periodicity alignment on the cube scan first")
    known_size: bool = Field(
        True,
        description="finish with an upright cube of the recipe's edge fitted to the faces "
        "(false: the box cost's result)",
    )


class SigmaLimits(Settings):
    """``calibration.max_sigma``: optional limits on the 1σ of single parameters, stricter than
    the accuracy budget (:class:`AccuracySettings`), which is what decides.

    A result with a larger σ is refused, with a message that names the parameter and what to
    do; a limit left out (the default) is not checked. ty is the gauge along the axis and has no
    limit. Lengths in metres, angles in degrees, the time offset (estimated when the spin scan has
    a second pass) in milliseconds.
    """

    tx: float | None = Field(None, gt=0, le=0.1)
    tz: float | None = Field(None, gt=0, le=0.1)
    ry_deg: float | None = Field(None, gt=0, le=10)
    rz_deg: float | None = Field(None, gt=0, le=10)
    encoder_latency_ms: float = Field(
        0.2, gt=0, le=100,
        description="the lidar–encoder time offset, when a second pass estimates it",
    )


class AccuracySettings(Settings):
    """``calibration.accuracy``: the accuracy budget, in the unit's own terms.

    ``max_error`` is the largest reconstruction error the station accepts (metres, at ``level``)
    over its *work volume*: a cylinder standing on the platter top, of ``radius`` (default the
    platter's) and ``height``. The error is the distortion of an object filling that volume —
    what is left of the reconstruction's displacement after the best rigid alignment — that the
    calibration's covariance (and any bias bound) allows (:mod:`calstation.engine.accuracy`).
    The default height, 0.15 m, is the tallest of the objects the paper scans (the 150 mm
    pyramid and prism; the QA cube is 100 mm): an ry error grows with the height, so a taller
    volume asks more of the calibration.
    """

    max_error: float = Field(
        0.0003, gt=0, le=0.1,
        description="largest reconstruction error accepted over the work volume, metres",
    )
    height: float = Field(0.15, gt=0, le=2.0, description="work volume above the platter, m")
    radius: float | None = Field(
        None, gt=0, le=1.5, description="work volume radius, m (default: the platter's)"
    )
    level: float = Field(0.95, ge=0.5, le=0.999, description="the error's confidence level")
    axis_sigma: float | None = Field(
        0.0001, gt=0, le=0.01,
        description="with a range model, the QA cube's scan also turns on (up to its "
        "max_revolutions) while the σ of where the axis lies, across it at the platter centre, "
        "is above this, m: H alone, as a URDF carries it without the range terms, is then within "
        "3σ of it (null: the budget alone)",
    )

    def work_radius(self, platter: PlatterGeometry) -> float:
        """The work volume's radius (m): this one's, else the platter's."""
        return self.radius if self.radius is not None else platter.radius


class QALimits(Settings):
    """Pass/fail limits of the cube check and drift alarms (metres and degrees)."""

    edge_error: float = Field(0.0010, ge=1e-6, le=0.1)
    obb_edge_error: float = Field(0.0060, ge=1e-6, le=0.1)
    flatness_rms: float = Field(
        0.0015, ge=1e-6, le=0.1,
        description="largest RMS of a face about its plane beyond what the range noise "
        "explains, m",
    )
    perpendicularity_deg: float = Field(0.5, ge=0.001, le=45)
    twist_deg: float = Field(
        0.1, ge=0.001, le=10,
        description="largest ry correction the cube's side faces may ask for beyond 3 of its "
        "σ (degrees)",
    )
    drift_translation: float = Field(0.002, ge=1e-6, le=1.0)
    drift_rotation_deg: float = Field(0.2, ge=0.001, le=45)
    drift_fails: bool = Field(
        False, description="drift beyond the limits fails the run (default: a warning only)"
    )


