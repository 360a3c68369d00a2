"""One clock in every recording: read with the official ``mcap`` reader and the Foxglove schemas
(not calstation's reader), every time in a simulated run's files lies within its scan's span,
and the calibration transform comes before the first scan."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from tests.support.one_clock import check_one_clock

DATA = Path(__file__).resolve().parents[1] / "data" / "v1"


def test_a_simulated_run_has_one_clock(sim_run: Callable[..., dict[str, Path]]) -> None:
    paths = sim_run(recipe=DATA / "recipe.yaml", seed=0)
    for kind in ("static", "spin", "cube"):
        check_one_clock(paths[kind])


def test_the_check_sees_a_second_clock(tmp_path: Path) -> None:
    """A file created on the host's clock around data on the simulated clock (what every
    recording did before) fails the check."""
    import numpy as np

    from calstation.clock import HostClock, SimClock
    from calstation.drivers import EncoderSample, LidarInfo, LidarLine
    from calstation.engine.frames import Extrinsics
    from calstation.recordings.writer import RecordingWriter

    info = LidarInfo("v", "m", "s", 1.0, 3, 100.0, 0.1, 10.0)
    sim = SimClock()
    for name, clock in (("one.mcap", sim), ("two.mcap", HostClock())):
        with RecordingWriter(tmp_path / name, kind="spin", lidar_info=info,
                             counts_per_revolution=4096, encoder_direction=1,
                             calibration=Extrinsics(0, 1, 0, 0, 0, -0.7), clock=clock) as w:
            t = sim.now_ns() + 1_000_000
            w.write_encoder([EncoderSample(t, 0), EncoderSample(t + 50_000_000, 100)])
            w.write_line(LidarLine(t, np.zeros(3), np.ones(3), np.ones(3, bool), 1e5))
    check_one_clock(tmp_path / "one.mcap")
    with pytest.raises(AssertionError, match="away from its first line"):
        check_one_clock(tmp_path / "two.mcap")
