"""The steps section of a recipe: how each scan is acquired."""

from __future__ import annotations

from pydantic import Field

from calstation.recipes.base import Model


class StaticScanStep(Model):
    """The static scan of the L-target."""

    lines: int = Field(100, ge=1, le=10_000)


class SpinScanStep(Model):
    """A spin scan (spin target or QA cube)."""

    rpm: float = Field(20.0, ge=0.5, le=120)
    revolutions: float = Field(1.05, ge=1.0, le=10.0, description="a little over one turn")
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

