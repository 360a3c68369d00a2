"""The static scan: lines at rest of the L-target → ``static.mcap``, and the initial
calibration from them (paper §III-A; the pipeline's first stage,
:func:`calstation.pipeline.stages.initial`)."""

from __future__ import annotations

from calstation.station.context import RunContext
from calstation.station.outcome import StepOutcome, format_h, plain
from calstation.station.recording_io import record_scan, static_acquisition


class StaticScan:
    """Record ``steps.static_scan.lines`` lines at rest and fit the initial calibration."""

    name = "static_scan"

    def run(self, ctx: RunContext, step_id: int) -> StepOutcome:
        """Scan, then fit the L-target; the recording and the ``initial`` calibration."""
        from calstation.pipeline.stages import initial
        from calstation.recordings.reader import read_recording

        d = ctx.hardware()
        lines = ctx.recipe.steps.static_scan.lines
        path = record_scan(ctx, self.name, step_id, static_acquisition(d, lines))
        recording = read_recording(path)
        with ctx.ui.progress("initial calibration") as progress:
            progress("fitting the L-target", 0.1)
            result = initial(ctx.recipe, recording).result
        ctx.ui.info(f"  initial: {format_h(result.H.as_dict(), result.sigma)}")
        return StepOutcome(
            {"recording": str(path), "lines": lines, "H": plain(result.H.as_dict())},
            artifacts=[("static", path)],
            calibration=("initial", result),
        )
