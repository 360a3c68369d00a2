"""One clock in every recording: read with the official ``mcap`` reader and the Foxglove schemas
(not calstation's reader), every time in a simulated run's files lies within its scan's span,
and the calibration transform comes before the first scan."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

DATA = Path(__file__).parent / "data" / "v1"
PREAMBLE_S = 60.0
"""At most this long between a file's creation and its first line (spin-up and settling)."""
SCAN_S = 600.0
"""At most this long from a scan's first datum to its last."""


def _stamp_ns(ts: Any) -> int:
    """A protobuf ``google.protobuf.Timestamp`` in ns."""
    return int(ts.seconds) * 1_000_000_000 + int(ts.nanos)


def _read(path: Path) -> dict[str, Any]:
    """Everything timed in ``path``, decoded with ``mcap`` + ``mcap-protobuf-support``."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    out: dict[str, Any] = {"messages": [], "stamps": [], "lines": [], "readings": []}
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        out["metadata"] = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        out["attachments"] = [(a.name, a.log_time, a.create_time)
                              for a in reader.iter_attachments()]
        for _, channel, message in reader.iter_messages(log_time_order=False):
            out["messages"].append((channel.topic, message.log_time, message.publish_time))
            if channel.topic == "/turntable/status":  # JSON
                out["readings"].append(int(json.loads(message.data)["timestamp_ns"]))
        f.seek(0)
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, _, msg in reader.iter_decoded_messages(
            topics=["/lidar/scan", "/tf", "/tf_static", "/platter/cloud", "/lidar/line",
                    "/encoder/count"],
            log_time_order=False,
        ):
            if channel.topic == "/encoder/count":
                out["readings"] += [int(t) for t in msg.timestamp_ns]
            elif channel.topic == "/lidar/line":
                offsets = list(msg.time_offset_ns)
                last = offsets[-1] if offsets else round((msg.count - 1) * msg.point_period_ns)
                out["lines"].append((int(msg.timestamp_ns), int(msg.timestamp_ns) + int(last)))
            else:
                assert schema.name.startswith("foxglove.")
                out["stamps"].append((channel.topic, _stamp_ns(msg.timestamp)))
        f.seek(0)
        summary = make_reader(f).get_summary()
        assert summary is not None and summary.statistics is not None
        out["statistics"] = (summary.statistics.message_start_time,
                             summary.statistics.message_end_time)
    return out


def check_one_clock(path: Path) -> None:
    """Every message's log and publish time, every Foxglove message's own timestamp, the
    attachment's times and ``created_ns`` lie within the scan's span: from its first datum or
    the file's creation, whichever is earlier (readings buffered by a driver may predate the
    file), to its last datum (the last point of the last line, the last encoder reading or
    turntable status); the calibration's ``/tf_static`` comes no later than the first scan."""
    got = _read(path)
    created = int(json.loads(got["metadata"]["calstation"]["created_ns"]))
    first_line = min(t0 for t0, _ in got["lines"])
    data = [t for line in got["lines"] for t in line] + got["readings"]
    start, end = min([created, *data]), max(data)
    assert abs(first_line - created) * 1e-9 < PREAMBLE_S, (
        f"{path.name}: created {(first_line - created) * 1e-9:+.0f} s away from its first line")
    assert (end - start) * 1e-9 < SCAN_S, f"{path.name}: spans {(end - start) * 1e-9:.0f} s"

    def inside(what: str, t: int) -> None:
        assert start <= t <= end, (
            f"{path.name}: {what} at {t} outside the scan's span [{start}, {end}] "
            f"({(t - start) * 1e-9:+.3f} s from the start)")

    for topic, log_time, publish_time in got["messages"]:
        inside(f"{topic} log time", log_time)
        inside(f"{topic} publish time", publish_time)
    for topic, stamp in got["stamps"]:
        inside(f"{topic} timestamp", stamp)
    for name, log_time, create_time in got["attachments"]:
        inside(f"attachment {name} log time", log_time)
        inside(f"attachment {name} create time", create_time)
    inside("created_ns", created)
    first, last = got["statistics"]
    inside("summary message_start_time", first)
    inside("summary message_end_time", last)
    if "calibration" in got["metadata"]:
        static = [t for topic, t, _ in got["messages"] if topic == "/tf_static"]
        scans = [t for topic, t, _ in got["messages"] if topic == "/lidar/scan"]
        assert static, f"{path.name}: a calibration record but no /tf_static"
        assert min(static) <= min(scans), f"{path.name}: the calibration arrives after a scan"


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
