"""The spin scan: the strategy's fixture turning at ``steps.spin_scan.rpm`` → ``spin.mcap``
(each line prepared for the fine-tuning as it arrives), and with ``second_pass_rpm`` the same
turns again at that speed → ``spin-pass2.mcap``, from which the fine-tuning estimates the
lidar–encoder time offset."""

from __future__ import annotations

from calstation.jsonvalue import JSONObject
from calstation.recordings.runfolder import second_pass
from calstation.station.context import RunContext
from calstation.station.outcome import StepOutcome, plain
from calstation.station.recording_io import record_scan, record_second_pass, spin_acquisition
from calstation.station.turns import more_turns

SECOND_PASS = second_pass("spin")
"""File stem and artifact kind of the spin scan's second pass (``second_pass_rpm``)."""


class SpinScan:
    """Record the spin scan (and its second pass)."""

    name = "spin_scan"

    def run(self, ctx: RunContext, step_id: int) -> StepOutcome:
        """Scan; the recordings (a fault in the second pass keeps the first as complete)."""
        d = ctx.hardware()
        cfg = ctx.recipe.steps.spin_scan
        path = record_scan(ctx, self.name, step_id, spin_acquisition(d, cfg),
                           more_turns=more_turns(ctx, "spin_scan"))
        result: JSONObject = {"recording": str(path), "rpm": cfg.rpm,
                                  "revolutions": cfg.revolutions,
                                  "fixture": ctx.strategy().fixture}
        prepared = ctx.prepared.get(path)
        if prepared is not None and prepared.turns is not None:
            result["turn_by_turn"] = plain(prepared.turns.summary)
        if prepared is not None:
            result["lost_lines"] = prepared.lost_lines
        artifacts = [("spin", path)]
        # the same turns again at another speed: the fine-tune estimates the lidar–encoder time
        # offset from the two
        path2 = record_second_pass(ctx, self.name, step_id, path, SECOND_PASS)
        if path2 is not None:
            result.update(second_pass={"recording": str(path2), "rpm": cfg.second_pass_rpm})
            artifacts.append((SECOND_PASS, path2))
        return StepOutcome(result, artifacts=artifacts)
