"""The steps section of a recipe: how each scan is acquired."""

from __future__ import annotations

from pydantic import Field

from calstation.recipes.base import Model


class StaticScanStep(Model):
    """The static scan of the L-target."""

    lines: int = Field(100, ge=1, le=10_000)


DEFAULT_MAX_REVOLUTIONS = 8.0
"""Turns a spin scan may take, by default, while its calibration's predicted error is above the
accuracy budget: the measured σ falls as 1/√turns, so 8 turns buy a σ 2.8 times smaller than
one, enough for the range noise of 2 mm (docs/algorithms.md); 8 turns at 20 rpm last 24 s, far
less than a re-placement and a new scan."""


class SpinScanStep(Model):
    """A spin scan (spin target or QA cube).

    It turns ``revolutions`` at least; then, while the calibration from the data so far predicts
    an error above ``calibration.accuracy.max_error``, one more revolution at a time, up to
    ``max_revolutions`` turns or ``max_duration_s`` seconds of scanning, whichever comes first.
    Without ``max_revolutions``, up to :data:`DEFAULT_MAX_REVOLUTIONS` turns, fewer where a
    longer scan would pass the limits of a scan (``calstation.recipes.validation.most_turns``);
    ``max_revolutions`` equal to ``revolutions`` scans exactly that.
    """

    rpm: float = Field(20.0, ge=0.5, le=120)
    revolutions: float = Field(1.05, ge=1.0, le=10.0, description="a little over one turn")
    max_revolutions: float | None = Field(
        None, ge=1.0, le=20.0,
        description="keep turning while the predicted error is above the budget, up to this "
        f"(default: {DEFAULT_MAX_REVOLUTIONS:g}, or fewer where a scan's limits say so)",
    )
    max_duration_s: float | None = Field(
        None, gt=0, le=600, description="and for at most this long (scanning time, s)"
    )
    settle_s: float = Field(0.5, ge=0, le=60)
    second_pass_rpm: float | None = Field(
        None, ge=-120, le=120,
        description="scan the same turns again at this signed speed (negative: the other way): "
        "the spin scan's two passes give the lidar–encoder time offset, the cube's are measured "
        "together, which shows whether that offset is right",
    )

    def second_pass(self) -> SpinScanStep | None:
        """The second pass as a scan of its own (this one at ``second_pass_rpm``), or None."""
        if self.second_pass_rpm is None:
            return None
        return self.model_copy(update={"rpm": self.second_pass_rpm, "second_pass_rpm": None})


class Steps(Model):
    """Acquisition settings per step."""

    static_scan: StaticScanStep = StaticScanStep()
    spin_scan: SpinScanStep = SpinScanStep()
    cube_scan: SpinScanStep = SpinScanStep()

