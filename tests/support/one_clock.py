"""One clock in a recording, checked with the official ``mcap`` reader and the Foxglove schemas
(not calstation's reader): :func:`check_one_clock`, for every test that writes a recording."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

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
