"""``settings`` of the ``sim`` drivers: a light module, so that a recipe's driver settings are
checked (``calstation recipes validate``) without importing the simulator and Open3D."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class SimSettings(BaseModel):
    """``settings`` of the ``sim`` drivers (checked by ``calstation recipes validate``)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    seed: int | None = Field(None, ge=0, le=2**63 - 1)
    range_m: float | None = Field(None, ge=0.2, le=20.0)
    pitch_deg: float | None = Field(None, gt=5, lt=85)
    real_time: bool = False
    """Run on the host's clock, at a real station's pace (a run takes as long as its scans and
    waits), rather than on a simulated clock that moves as fast as the computation."""
