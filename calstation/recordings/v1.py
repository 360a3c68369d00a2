"""Reading version-1 recordings: one JSON message per lidar line or encoder batch, arrays in
base64.

calstation writes version 2 (:mod:`calstation.recordings.writer`); version-1 files, written by
calstation before the protobuf layout, are still read. :mod:`calstation.recordings.reader` walks
the file and hands each JSON message of ``/lidar/line`` or ``/encoder/count`` to
:func:`collect_message_v1`, then builds the arrays with :func:`lines_v1`.
"""

from __future__ import annotations

import base64
from pathlib import Path
from typing import Any

import numpy as np

from calstation.errors import RecordingError
from calstation.recordings.channels import ENCODER_TOPIC, LIDAR_TOPIC
from calstation.recordings.collected import Collected, Lines

# dtypes of the version-1 base64 arrays (little-endian)
V1_AZIMUTH_DTYPE = np.dtype("<f8")
V1_RANGE_DTYPE = np.dtype("<f4")
V1_VALID_DTYPE = np.dtype("u1")
V1_INTENSITY_DTYPE = np.dtype("<f4")
V1_TIME_OFFSET_DTYPE = np.dtype("<i8")


def collect_message_v1(
    p: Path, col: Collected, topic: str, msg: dict[str, Any]  # Any: the message's JSON
) -> None:
    """Add a version-1 JSON message (base64 arrays) of ``/lidar/line`` or ``/encoder/count`` to
    ``col``; :class:`RecordingError` names the file ``p`` when its arrays do not fit."""
    if topic == ENCODER_TOPIC:
        ts, cs = msg["timestamp_ns"], msg["count"]
        if len(ts) != len(cs):
            raise RecordingError(
                f"recording {p}: an encoder message has {len(ts)} timestamps for "
                f"{len(cs)} counts"
            )
        col.enc_t.extend(int(t) for t in ts)
        col.enc_c.extend(int(c) for c in cs)
        return
    if topic != LIDAR_TOPIC:
        raise RecordingError(f"recording {p}: a JSON message on {topic} (a version-2 topic)")
    n = int(msg["count"])
    col.line_ts.append(int(msg["timestamp_ns"]))
    col.line_period.append(float(msg["point_period_ns"]))
    col.line_count.append(n)
    arrays: dict[str, np.dtype[np.generic]] = {
        "azimuth_rad": V1_AZIMUTH_DTYPE,
        "range_m": V1_RANGE_DTYPE,
        "valid": V1_VALID_DTYPE,
        "time_offset_ns": V1_TIME_OFFSET_DTYPE,
        "intensity": V1_INTENSITY_DTYPE,
    }
    raw: dict[str, bytes | None] = {}
    for name, dtype in arrays.items():
        if name not in msg:
            if name in ("azimuth_rad", "range_m", "valid"):
                raise KeyError(name)
            raw[name] = None
            continue
        raw[name] = b = base64.b64decode(msg[name])
        if len(b) != n * dtype.itemsize:
            raise RecordingError(
                f"recording {p}: lidar line {len(col.line_ts) - 1} field {name} has "
                f"{len(b)} bytes, expected {n * dtype.itemsize} for {n} points"
            )
    col.azimuth.append(raw["azimuth_rad"] or b"")
    col.range_.append(raw["range_m"] or b"")
    col.valid.append(raw["valid"] or b"")
    col.line_offsets.append(raw["time_offset_ns"])
    col.intensity.append(raw["intensity"])


def lines_v1(col: Collected) -> Lines:
    """The per-line and per-point arrays of the version-1 lines collected in ``col``."""
    return Lines(
        line_ts=np.asarray(col.line_ts, dtype=np.int64),
        periods=np.asarray(col.line_period, dtype=np.float64),
        counts=np.asarray(col.line_count, dtype=np.int64),
        azimuth=np.frombuffer(b"".join(col.azimuth), V1_AZIMUTH_DTYPE).astype(np.float64),
        range_m=np.frombuffer(b"".join(col.range_), V1_RANGE_DTYPE).astype(np.float64),
        valid=np.frombuffer(b"".join(col.valid), V1_VALID_DTYPE).astype(bool),
        offsets=col.line_offsets,
        intensity=col.intensity,
        intensity_dtype=V1_INTENSITY_DTYPE,
    )

