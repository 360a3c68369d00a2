"""The messages of a version-2 recording and of the live view, in well-known protobuf schemas.

- ``foxglove.LaserScan``: one lidar line in frame ``lidar`` (L), for viewers.
- ``calstation.LidarLineTiming``: the same line's exact azimuths, validity and timing.
- ``calstation.EncoderSamples``: a batch of raw encoder readings.
- ``foxglove.FrameTransform``: the platter angle (``platform`` → ``platter``) and the calibration
  (``lidar`` → ``platform``).
- ``foxglove.PointCloud``: a reconstructed cloud (float32 x, y, z).

Encoders write the protobuf wire format directly (packed arrays from ``tobytes()``); decoders
return the packed arrays as buffers for ``numpy.frombuffer``. The foxglove schemas are the
official ones shipped by ``foxglove-sdk``; calstation's own are built in :mod:`protowire`.
See ``docs/recording-format.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calstation.errors import RecordingError
from calstation.recordings import protowire as pw

LIDAR_FRAME = "lidar"
PLATFORM_FRAME = "platform"
PLATTER_FRAME = "platter"

LINE_TIMING_SCHEMA = "calstation.LidarLineTiming"
ENCODER_SCHEMA = "calstation.EncoderSamples"

AZIMUTH_DTYPE = np.dtype("<f8")
RANGE_DTYPE = np.dtype("<f8")
VALID_DTYPE = np.dtype("u1")
INTENSITY_DTYPE = np.dtype("<f8")
TIME_DTYPE = np.dtype("<i8")

_CALSTATION_PROTO = pw.file_descriptor_set(
    "calstation/recording.proto",
    "calstation",
    [
        (
            "LidarLineTiming",
            [
                ("timestamp_ns", 1, pw.TYPE_INT64, pw.LABEL_OPTIONAL),
                ("point_period_ns", 2, pw.TYPE_DOUBLE, pw.LABEL_OPTIONAL),
                ("count", 3, pw.TYPE_UINT32, pw.LABEL_OPTIONAL),
                ("azimuth_rad", 4, pw.TYPE_DOUBLE, pw.LABEL_REPEATED),
                ("valid", 5, pw.TYPE_BOOL, pw.LABEL_REPEATED),
                ("time_offset_ns", 6, pw.TYPE_SFIXED64, pw.LABEL_REPEATED),
                ("invalid_range_m", 7, pw.TYPE_DOUBLE, pw.LABEL_REPEATED),
            ],
        ),
        (
            "EncoderSamples",
            [
                ("timestamp_ns", 1, pw.TYPE_SFIXED64, pw.LABEL_REPEATED),
                ("count", 2, pw.TYPE_SFIXED64, pw.LABEL_REPEATED),
            ],
        ),
    ],
)


@dataclass(frozen=True)
class SchemaData:
    """An MCAP schema: name, encoding and data (a serialised FileDescriptorSet)."""

    name: str
    encoding: str
    data: bytes


@cache
def schema(name: str) -> SchemaData:
    """The protobuf schema ``name`` (``foxglove.LaserScan``, ``calstation.EncoderSamples``, …)."""
    if name.startswith("calstation."):
        return SchemaData(name, "protobuf", _CALSTATION_PROTO)
    import foxglove.messages as fm

    cls = getattr(fm, name.removeprefix("foxglove."))
    s = cls.get_schema()
    return SchemaData(str(s.name), str(s.encoding), bytes(s.data))


# --- encoding ------------------------------------------------------------------------------
def _timestamp(t_ns: int) -> bytes:
    sec, nsec = divmod(int(t_ns), 1_000_000_000)
    return pw.varint_field(1, sec) + pw.varint_field(2, nsec)


def _vector3(x: float, y: float, z: float) -> bytes:
    return pw.double_field(1, x) + pw.double_field(2, y) + pw.double_field(3, z)


def _quaternion(q: ArrayLike) -> bytes:
    x, y, z, w = (float(v) for v in np.asarray(q, dtype=np.float64).reshape(4))
    return _vector3(x, y, z) + pw.double_field(4, w)


_IDENTITY_POSE = pw.len_field(1, _vector3(0.0, 0.0, 0.0)) + pw.len_field(
    2, _quaternion([0.0, 0.0, 0.0, 1.0])
)


def laser_scan(
    timestamp_ns: int,
    azimuth_rad: ArrayLike,
    range_m: ArrayLike,
    valid: ArrayLike,
    intensity: ArrayLike | None = None,
) -> bytes:
    """A ``foxglove.LaserScan`` of one line in frame ``lidar`` (L).

    LaserScan bearings turn counter-clockwise from +X; calstation's azimuth α turns from +Y_L
    toward +X_L, so the bearing is ``π/2 − α`` (the point ``(ρ·sin α, ρ·cos α, 0)`` either way).
    Bearings are assumed equally spaced from the first to the last point: the exact azimuths are
    in :func:`line_timing`. Invalid returns are NaN ranges.
    """
    az = np.asarray(azimuth_rad, dtype=np.float64)
    rng = np.array(range_m, dtype=RANGE_DTYPE)
    rng[~np.asarray(valid, dtype=bool)] = np.nan
    n = len(az)
    start = math.pi / 2 - float(az[0]) if n else 0.0
    end = math.pi / 2 - float(az[-1]) if n else 0.0
    out = (
        pw.len_field(1, _timestamp(timestamp_ns))
        + pw.string_field(2, LIDAR_FRAME)
        + pw.len_field(3, _IDENTITY_POSE)
        + pw.double_field(4, start)
        + pw.double_field(5, end)
        + pw.len_field(6, rng.tobytes())
    )
    if intensity is not None:
        out += pw.len_field(7, np.ascontiguousarray(intensity, INTENSITY_DTYPE).tobytes())
    return out


def line_timing(
    timestamp_ns: int,
    point_period_ns: float,
    azimuth_rad: ArrayLike,
    range_m: ArrayLike,
    valid: ArrayLike,
    time_offset_ns: ArrayLike | None = None,
) -> bytes:
    """A ``calstation.LidarLineTiming``: exact azimuths, validity and per-point timing, and the
    raw ranges of the invalid returns (NaN in the LaserScan), in point order."""
    az = np.ascontiguousarray(azimuth_rad, dtype=AZIMUTH_DTYPE)
    ok = np.ascontiguousarray(valid, dtype=bool)
    out = (
        pw.varint_field(1, int(timestamp_ns))
        + pw.double_field(2, float(point_period_ns))
        + pw.varint_field(3, len(az))
        + pw.len_field(4, az.tobytes())
        + pw.len_field(5, ok.view(VALID_DTYPE).tobytes())
    )
    if time_offset_ns is not None:
        out += pw.len_field(6, np.ascontiguousarray(time_offset_ns, dtype=TIME_DTYPE).tobytes())
    if not ok.all():
        bad = np.asarray(range_m, dtype=RANGE_DTYPE)[~ok]
        out += pw.len_field(7, np.ascontiguousarray(bad).tobytes())
    return out


def encoder_samples(timestamp_ns: ArrayLike, count: ArrayLike) -> bytes:
    """A ``calstation.EncoderSamples`` batch (host times in ns, unwrapped signed counts)."""
    return pw.len_field(1, np.ascontiguousarray(timestamp_ns, TIME_DTYPE).tobytes()) + (
        pw.len_field(2, np.ascontiguousarray(count, TIME_DTYPE).tobytes())
    )


def frame_transform(
    timestamp_ns: int, parent: str, child: str, translation: ArrayLike, quaternion_xyzw: ArrayLike
) -> bytes:
    """A ``foxglove.FrameTransform``: the pose of ``child`` in ``parent`` (metres; quaternion
    x, y, z, w)."""
    tx, ty, tz = (float(v) for v in np.asarray(translation, dtype=np.float64).reshape(3))
    return (
        pw.len_field(1, _timestamp(timestamp_ns))
        + pw.string_field(2, parent)
        + pw.string_field(3, child)
        + pw.len_field(4, _vector3(tx, ty, tz))
        + pw.len_field(5, _quaternion(quaternion_xyzw))
    )


def platter_transform(timestamp_ns: int, phi: float) -> bytes:
    """The platter angle φ as a ``foxglove.FrameTransform`` ``platform`` → ``platter``
    (``p_P = Rx(φ)·p_D``)."""
    half = 0.5 * float(phi)
    return frame_transform(
        timestamp_ns, PLATFORM_FRAME, PLATTER_FRAME, (0.0, 0.0, 0.0),
        (math.sin(half), 0.0, 0.0, math.cos(half)),
    )


_FLOAT32 = 7  # foxglove.PackedElementField.NumericType.FLOAT32
_XYZ_FIELDS = b"".join(
    pw.len_field(
        5, pw.string_field(1, name) + pw.fixed32_field(2, 4 * i) + pw.varint_field(3, _FLOAT32)
    )
    for i, name in enumerate("xyz")
)


def point_cloud(timestamp_ns: int, frame_id: str, points: ArrayLike) -> bytes:
    """A ``foxglove.PointCloud`` of (N, 3) points in ``frame_id`` (metres), float32 x, y, z."""
    p = np.ascontiguousarray(points, dtype="<f4").reshape(-1, 3)
    return (
        pw.len_field(1, _timestamp(timestamp_ns))
        + pw.string_field(2, frame_id)
        + pw.len_field(3, _IDENTITY_POSE)
        + pw.fixed32_field(4, 12)
        + _XYZ_FIELDS
        + pw.len_field(6, p.tobytes())
    )


# --- decoding ------------------------------------------------------------------------------
Buffer = bytes | memoryview


def _timestamp_ns(value: int | bytes | memoryview) -> int:
    if isinstance(value, int):
        raise RecordingError("malformed protobuf: a timestamp is not a message")
    # the usual layout (sec = 1, nsec = 2, both varints) read directly: one per lidar line
    sec = nsec = pos = 0
    n = len(value)
    while pos < n:
        key = value[pos]
        if key not in (0x08, 0x10):
            return _timestamp_fields(value)
        v, pos = pw.read_varint(value, pos + 1)
        if key == 0x08:
            sec = pw.as_int64(v)
        else:
            nsec = pw.as_int64(v)
    return sec * 1_000_000_000 + nsec


def _timestamp_fields(value: bytes | memoryview) -> int:
    sec = nsec = 0
    for f, _, v in pw.fields(value):
        if f == 1:
            sec = pw.as_int64(v)
        elif f == 2:
            nsec = pw.as_int64(v)
    return sec * 1_000_000_000 + nsec


def _buf(value: int | bytes | memoryview, what: str) -> Buffer:
    if isinstance(value, int):
        raise RecordingError(f"malformed protobuf: {what} is not length-delimited")
    return value


@dataclass
class ScanFields:
    """The fields of a ``foxglove.LaserScan`` a reader needs (buffers of packed doubles)."""

    timestamp_ns: int
    ranges: Buffer
    intensities: Buffer | None


def decode_laser_scan(data: Buffer) -> ScanFields:
    """The timestamp, ranges and intensities of a ``foxglove.LaserScan``."""
    return ScanFields(*laser_scan_parts(data))


def laser_scan_parts(data: Buffer) -> tuple[int, Buffer, Buffer | None]:
    """(timestamp ns, ranges, intensities or None) of a ``foxglove.LaserScan``."""
    ts = 0
    ranges: Buffer = b""
    intensities: Buffer | None = None
    for f, _, v in pw.fields(data):
        if f == 1:
            ts = _timestamp_ns(v)
        elif f == 6:
            ranges = _buf(v, "ranges")
        elif f == 7:
            intensities = _buf(v, "intensities")
    if intensities is not None and len(intensities) == 0:
        intensities = None
    return ts, ranges, intensities


@dataclass
class TimingFields:
    """A decoded ``calstation.LidarLineTiming`` (buffers of packed arrays)."""

    timestamp_ns: int
    point_period_ns: float
    count: int
    azimuth: Buffer
    valid: Buffer
    time_offset: Buffer | None
    invalid_range: Buffer


def decode_line_timing(data: Buffer) -> TimingFields:
    """Decode a ``calstation.LidarLineTiming``."""
    return TimingFields(*line_timing_parts(data))


def line_timing_parts(
    data: Buffer,
) -> tuple[int, float, int, Buffer, Buffer, Buffer | None, Buffer]:
    """The fields of a ``calstation.LidarLineTiming`` as a tuple, in :class:`TimingFields`'
    order."""
    ts = count = 0
    period = 0.0
    azimuth: Buffer = b""
    valid: Buffer = b""
    offsets: Buffer | None = None
    invalid: Buffer = b""
    for f, _, v in pw.fields(data):
        if f == 1:
            ts = pw.as_int64(v)
        elif f == 2:
            period = pw.as_double(v)
        elif f == 3:
            count = pw.as_int64(v)
        elif f == 4:
            azimuth = _buf(v, "azimuth_rad")
        elif f == 5:
            valid = _buf(v, "valid")
        elif f == 6:
            offsets = _buf(v, "time_offset_ns")
        elif f == 7:
            invalid = _buf(v, "invalid_range_m")
    return ts, period, count, azimuth, valid, offsets, invalid


def decode_encoder_samples(data: Buffer) -> tuple[Buffer, Buffer]:
    """(timestamps, counts) of a ``calstation.EncoderSamples``: buffers of little-endian int64."""
    t: Buffer = b""
    c: Buffer = b""
    for f, _, v in pw.fields(data):
        if f == 1:
            t = _buf(v, "timestamp_ns")
        elif f == 2:
            c = _buf(v, "count")
    return t, c


@dataclass(frozen=True)
class Transform:
    """A decoded ``foxglove.FrameTransform``."""

    timestamp_ns: int
    parent: str
    child: str
    translation: NDArray[np.float64]
    quaternion_xyzw: NDArray[np.float64]


def _doubles(value: int | bytes | memoryview, n: int) -> NDArray[np.float64]:
    out = np.zeros(n)  # proto3 leaves zero fields out
    for f, _, v in pw.fields(_buf(value, "vector")):
        if 1 <= f <= n:
            out[f - 1] = pw.as_double(v)
    return out


def decode_frame_transform(data: Buffer) -> Transform:
    """Decode a ``foxglove.FrameTransform``."""
    ts, parent, child = 0, "", ""
    trans, quat = np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0])
    for f, _, v in pw.fields(data):
        if f == 1:
            ts = _timestamp_ns(v)
        elif f == 2:
            parent = bytes(_buf(v, "parent_frame_id")).decode("utf-8")
        elif f == 3:
            child = bytes(_buf(v, "child_frame_id")).decode("utf-8")
        elif f == 4:
            trans = _doubles(v, 3)
        elif f == 5:
            quat = _doubles(v, 4)
    return Transform(ts, parent, child, trans, quat)
