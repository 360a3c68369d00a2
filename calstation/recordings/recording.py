"""Recordings: each scan written to MCAP while it is acquired, and read back as numpy arrays.

The format is documented in ``docs/recording-format.md``. In short (format version 2):

- MCAP, chunked (~1 MiB per chunk), zstd-compressed; the file is flushed after every chunk (and at
  least every second) so that a writer killed mid-scan loses at most the chunk in progress.
- Protobuf messages in well-known schemas, so viewers show the scan in 3D: each lidar line is a
  ``foxglove.LaserScan`` on ``/lidar/scan`` (frame ``lidar``) with its exact azimuths and timing
  in a ``calstation.LidarLineTiming`` on ``/lidar/line``; the encoder readings are
  ``calstation.EncoderSamples`` on ``/encoder/count`` and the platter angle a
  ``foxglove.FrameTransform`` stream on ``/tf``; the calibration, once known, a
  ``foxglove.FrameTransform`` on ``/tf_static``; the reconstructed cloud a ``foxglove.PointCloud``
  on ``/platter/cloud``. Turntable status stays JSON on ``/turntable/status``.
- Metadata records ``calstation``, ``lidar``, ``encoder`` (and ``truth`` for simulated data,
  ``calibration`` once known, or any other name); each value is JSON-encoded.
- The recipe text is the attachment ``recipe.yaml``.

Version-1 files (JSON messages with base64 arrays) are still read. :func:`read_recording` returns
a :class:`Recording` with flat numpy arrays (one entry per point).
"""

from __future__ import annotations

import base64
import binascii
import contextlib
import functools
import json
import math
import os
import threading
import time
import warnings
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calstation.drivers import EncoderSample, LidarInfo, LidarLine, TurntableState, TurntableStatus
from calstation.engine.frames import Extrinsics, counts_to_angle
from calstation.engine.scan import (
    Scan,
    encoder_angle as encoder_angle,  # re-exported
)
from calstation.errors import CalstationError, RecordingError
from calstation.recipes import LoadedRecipe
from calstation.recordings import messages as pb

FORMAT_VERSION: int = 2
"""Version of the recording layout (channels, schemas, metadata) described in the docs."""

SCAN_TOPIC = "/lidar/scan"
LIDAR_TOPIC = "/lidar/line"
ENCODER_TOPIC = "/encoder/count"
PLATTER_TF_TOPIC = "/tf"
STATIC_TF_TOPIC = "/tf_static"
CLOUD_TOPIC = "/platter/cloud"
TURNTABLE_TOPIC = "/turntable/status"
RECIPE_ATTACHMENT = "recipe.yaml"
RESERVED_METADATA = ("calstation", "lidar", "encoder", "calibration")

DEFAULT_CHUNK_SIZE = 1 << 20
"""Uncompressed bytes per chunk: a crash loses at most about this much of the scan."""
DEFAULT_FLUSH_INTERVAL_S = 1.0
"""A chunk is also closed and flushed when this much wall time passed since the last flush."""
DEFAULT_CLOUD_POINTS = 300_000
"""At most this many points in the reconstructed cloud written at the end of a scan."""

# dtypes of the version-1 base64 arrays (little-endian)
V1_AZIMUTH_DTYPE = np.dtype("<f8")
V1_RANGE_DTYPE = np.dtype("<f4")
V1_VALID_DTYPE = np.dtype("u1")
V1_INTENSITY_DTYPE = np.dtype("<f4")
V1_TIME_OFFSET_DTYPE = np.dtype("<i8")


class RecordingTruncatedWarning(UserWarning):
    """A recording was not closed cleanly (its writer was killed); it was read up to its last
    complete chunk."""


class LiveSink(Protocol):
    """Where a writer also sends every message as it is written (the live view)."""

    def publish(self, topic: str, schema: pb.SchemaData, data: bytes, log_time_ns: int) -> None:
        """Send one encoded message of ``topic`` (in ``schema``) stamped ``log_time_ns``."""
        ...


_live_sink: LiveSink | None = None


def set_live_sink(sink: LiveSink | None) -> None:
    """Make ``sink`` the live sink of every writer created from now on in this process (the
    live view, :mod:`calstation.recordings.liveview`); None stops it."""
    global _live_sink
    _live_sink = sink


def live_sink() -> LiveSink | None:
    """The process's live sink, if any."""
    return _live_sink


TURNTABLE_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "calstation.TurntableStatus",
    "description": "A status report of the turntable drive.",
    "type": "object",
    "properties": {
        "timestamp_ns": {"type": "integer", "description": "host-clock time, ns"},
        "state": {"type": "string", "enum": [s.value for s in TurntableState]},
        "speed_rpm": {"type": "number", "description": "signed speed, rpm"},
        "position_rad": {"type": ["number", "null"], "description": "position, rad, if known"},
        "faults": {"type": "array", "items": {"type": "string"}},
    },
    "required": ["timestamp_ns", "state", "speed_rpm"],
}
_TURNTABLE = pb.SchemaData(
    "calstation.TurntableStatus", "jsonschema", json.dumps(TURNTABLE_SCHEMA).encode("utf-8")
)

CHANNELS: dict[str, tuple[str, str]] = {
    SCAN_TOPIC: ("foxglove.LaserScan", "protobuf"),
    LIDAR_TOPIC: (pb.LINE_TIMING_SCHEMA, "protobuf"),
    ENCODER_TOPIC: (pb.ENCODER_SCHEMA, "protobuf"),
    PLATTER_TF_TOPIC: ("foxglove.FrameTransform", "protobuf"),
    STATIC_TF_TOPIC: ("foxglove.FrameTransform", "protobuf"),
    CLOUD_TOPIC: ("foxglove.PointCloud", "protobuf"),
    TURNTABLE_TOPIC: ("calstation.TurntableStatus", "json"),
}
"""Topic → (schema name, message encoding) of a version-2 recording."""


def channel_schema(topic: str) -> pb.SchemaData:
    """The schema of a version-2 ``topic``."""
    name = CHANNELS[topic][0]
    return _TURNTABLE if name == _TURNTABLE.name else pb.schema(name)


# --- writing -------------------------------------------------------------------------------
def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, Mapping):
        return dict(obj)
    if isinstance(obj, (set, frozenset, tuple)):
        return list(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def _encode_metadata(name: str, data: Mapping[str, Any]) -> dict[str, str]:
    out: dict[str, str] = {}
    for key, value in data.items():
        try:
            out[str(key)] = json.dumps(value, default=_json_default)
        except (TypeError, ValueError) as exc:
            raise RecordingError(
                f"metadata {name!r} key {key!r} cannot be stored as JSON: {exc}"
            ) from exc
    return out


def _calibration_record(H: Extrinsics, source: str) -> dict[str, Any]:
    return {**H.as_dict(), "source": source}


@dataclass
class _CloudBuffer:
    """What the writer keeps of a scan to reconstruct its cloud at the end (array references)."""

    lines: list[LidarLine] = field(default_factory=list)
    enc_t: list[int] = field(default_factory=list)
    enc_c: list[int] = field(default_factory=list)


class RecordingWriter:
    """Writes one scan to an MCAP file while it is acquired. A context manager.

    ``kind`` says what the scan is (``"static"``, ``"spin"``, ``"cube"`` or free text);
    ``lidar_info``, ``counts_per_revolution``, ``encoder_direction`` (+1/−1) and
    ``encoder_latency_s`` (encoder time minus lidar time, s) describe the station and are stored as
    metadata, with ``station_id``, the recipe's name and sha256 (its text becomes the attachment
    ``recipe.yaml``) and any further ``metadata`` records (name → mapping, e.g. ``"truth"``).

    ``calibration`` (with ``calibration_source``, e.g. ``"initial"``, ``"fine"``, ``"truth"``) is
    the H known when the scan starts: it is written as the ``calibration`` metadata record and the
    static transform ``lidar`` → ``platform``, and at the end of a scan that completed the
    reconstructed cloud (at most ``cloud_points`` points, frame ``platter``) is added.
    ``live`` receives every message as it is written (default: the process's live sink, see
    :func:`set_live_sink` and :mod:`calstation.recordings.liveview`).

    Data is buffered into chunks of about ``chunk_size`` uncompressed bytes; each finished chunk is
    compressed, written and flushed to the operating system at once, and a chunk is also closed
    after ``flush_interval_s`` of wall time, so a killed writer loses at most that much.
    Timestamps are host-clock ns since the Unix epoch and must not be negative.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        kind: str,
        lidar_info: LidarInfo,
        counts_per_revolution: int,
        encoder_direction: int,
        encoder_latency_s: float = 0.0,
        station_id: str = "",
        recipe: LoadedRecipe | None = None,
        metadata: Mapping[str, Mapping[str, Any]] | None = None,
        calibration: Extrinsics | None = None,
        calibration_source: str = "",
        live: LiveSink | None = None,
        cloud_points: int = DEFAULT_CLOUD_POINTS,
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        flush_interval_s: float = DEFAULT_FLUSH_INTERVAL_S,
    ) -> None:
        from mcap.writer import CompressionType, Writer

        _check_station(kind, counts_per_revolution, encoder_direction, encoder_latency_s, metadata)
        created_ns = time.time_ns()
        records = {
            "calstation": {
                "format_version": FORMAT_VERSION,
                "kind": kind,
                "station_id": station_id,
                "recipe_name": recipe.recipe.name if recipe is not None else "",
                "recipe_sha256": recipe.sha256 if recipe is not None else "",
                "created_ns": created_ns,
            },
            "lidar": lidar_info.as_dict(),
            "encoder": {
                "counts_per_revolution": int(counts_per_revolution),
                "direction": int(encoder_direction),
                "latency_s": float(encoder_latency_s),
            },
            **dict(metadata or {}),
        }
        if calibration is not None:
            records["calibration"] = _calibration_record(calibration, calibration_source)
        # encode everything before creating the file, so bad metadata leaves no file behind
        encoded = {name: _encode_metadata(name, data) for name, data in records.items()}

        self.path = Path(path)
        self._lock = threading.RLock()
        self._chunk_size = int(chunk_size)
        self._flush_interval_s = float(flush_interval_s)
        self._cpr = int(counts_per_revolution)
        self._direction = int(encoder_direction)
        self._latency_ns = round(encoder_latency_s * 1e9)
        self._live = live if live is not None else _live_sink
        self._cloud_points = int(cloud_points)
        self._calibration = calibration
        self._cloud = _CloudBuffer()
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file: IO[bytes] = open(self.path, "wb")  # noqa: SIM115 (closed in close())
        except OSError as exc:
            raise RecordingError(f"cannot create recording {self.path}: {exc}") from exc
        # the mcap writer never closes a chunk on its own: this class decides (size or time)
        # and flushes the file right after, so finished chunks are on disk during the scan
        self._writer = Writer(self._file, chunk_size=1 << 62, compression=CompressionType.ZSTD)
        self._closed = False
        self._pending = 0
        self._last_flush = time.monotonic()
        self._sequence: dict[int, int] = {}
        self._channels: dict[str, int] = {}
        self.lines_written = 0
        self.points_written = 0
        self.encoder_samples_written = 0
        try:
            self._writer.start(profile="", library=f"calstation recording v{FORMAT_VERSION}")
            for name, data in encoded.items():
                self._writer.add_metadata(name, data)
            if recipe is not None:
                self._writer.add_attachment(
                    create_time=created_ns,
                    log_time=created_ns,
                    name=RECIPE_ATTACHMENT,
                    media_type="application/yaml",
                    data=recipe.text.encode("utf-8"),
                )
            self._register_channels()
            self._file.flush()
        except OSError as exc:
            self._closed = True
            self._file.close()
            raise RecordingError(f"cannot write recording {self.path}: {exc}") from exc
        if calibration is not None:
            self._add(STATIC_TF_TOPIC, created_ns, _static_transform(created_ns, calibration))

    # --- public API ----------------------------------------------------------------------
    def write_line(self, line: LidarLine) -> None:
        """Append one lidar line (stamped on the host clock)."""
        ts = int(line.timestamp_ns)
        scan = pb.laser_scan(ts, line.azimuth_rad, line.range_m, line.valid, line.intensity)
        timing = pb.line_timing(
            ts, line.point_period_ns, line.azimuth_rad, line.range_m, line.valid,
            line.time_offset_ns,
        )
        with self._lock:
            self._add(SCAN_TOPIC, ts, scan)
            self._add(LIDAR_TOPIC, ts, timing)
            self.lines_written += 1
            self.points_written += len(line)
            if self._calibration is not None:
                self._cloud.lines.append(line)

    def write_encoder(self, samples: Iterable[EncoderSample]) -> None:
        """Append encoder readings (oldest first), batched into one message; the platter angle
        of the newest reading also goes to ``/tf`` (``platform`` → ``platter``)."""
        batch = list(samples)
        if not batch:
            return
        t = [int(s.timestamp_ns) for s in batch]
        c = [int(s.count) for s in batch]
        data = pb.encoder_samples(t, c)
        phi = float(counts_to_angle(c[-1], self._cpr, self._direction))
        t_lidar = max(t[-1] - self._latency_ns, 0)
        with self._lock:
            self._add(ENCODER_TOPIC, t[0], data)
            self._add(PLATTER_TF_TOPIC, t_lidar, pb.platter_transform(t_lidar, phi))
            self.encoder_samples_written += len(batch)
            if self._calibration is not None:
                self._cloud.enc_t.extend(t)
                self._cloud.enc_c.extend(c)

    def write_turntable(self, status: TurntableStatus) -> None:
        """Append one turntable status report."""
        data = json.dumps(status.as_dict(), separators=(",", ":")).encode("utf-8")
        with self._lock:
            self._add(TURNTABLE_TOPIC, int(status.timestamp_ns), data)

    def write_point_cloud(self, points: ArrayLike, timestamp_ns: int, frame_id: str) -> None:
        """Append a ``foxglove.PointCloud`` of (N, 3) points (metres) in ``frame_id``."""
        with self._lock:
            data = pb.point_cloud(timestamp_ns, frame_id, points)
            self._add(CLOUD_TOPIC, int(timestamp_ns), data)

    def add_metadata(self, name: str, data: Mapping[str, Any]) -> None:
        """Add a metadata record (e.g. ``"truth"``); values must be JSON-serialisable.

        A later record of the same name replaces an earlier one when the file is read.
        """
        if name in RESERVED_METADATA:
            raise RecordingError(f"metadata record {name!r} is written by the recorder itself")
        with self._lock:
            self._check_open()
            self._write_metadata(name, data)
            self._file.flush()

    def flush(self) -> None:
        """Close the chunk in progress and flush everything to the operating system."""
        with self._lock:
            self._check_open()
            self._flush()

    def close(self) -> None:
        """Finish the file (summary, indexes, footer), fsync it and close it. Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            try:
                self._writer.finish()  # type: ignore[no-untyped-call]
                self._file.flush()
                os.fsync(self._file.fileno())
            except OSError as exc:
                raise RecordingError(f"cannot finish recording {self.path}: {exc}") from exc
            finally:
                self._file.close()

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: object
    ) -> None:
        """Close the file; if the block raised, first add an ``aborted`` metadata record
        (``error``: the exception's type and message), so the partial scan says why it ended;
        otherwise first add the reconstructed cloud when the calibration is known."""
        try:
            if exc is not None and not self._closed:
                with contextlib.suppress(Exception):
                    self.add_metadata("aborted", {"error": f"{type(exc).__name__}: {exc}"})
            elif exc is None and not self._closed:
                self._write_cloud()
        finally:
            self.close()

    # --- internals -----------------------------------------------------------------------
    def _check_open(self) -> None:
        if self._closed:
            raise RecordingError(f"recording {self.path} is already closed")

    def _write_metadata(self, name: str, data: Mapping[str, Any]) -> None:
        self._writer.add_metadata(name, _encode_metadata(name, data))

    def _register_channels(self) -> None:
        schema_ids: dict[str, int] = {}
        for topic, (schema_name, encoding) in CHANNELS.items():
            if schema_name not in schema_ids:
                s = channel_schema(topic)
                schema_ids[schema_name] = self._writer.register_schema(
                    name=s.name, encoding=s.encoding, data=s.data
                )
            self._channels[topic] = self._writer.register_channel(
                topic=topic, message_encoding=encoding, schema_id=schema_ids[schema_name]
            )

    def _write_cloud(self) -> None:
        """The reconstructed cloud of the scan in frame D (``platter``), decimated."""
        buf, H = self._cloud, self._calibration
        if H is None or not buf.lines or not buf.enc_t:
            return
        from calstation.engine.reconstruct import reconstruct

        try:
            rec = _recording_from_lines(self, buf, self._cloud_points)
            points = reconstruct(rec, H)
        except Exception as exc:  # a preview: the scan itself is complete and kept
            warnings.warn(
                f"recording {self.path}: no reconstructed cloud written ({exc})", stacklevel=3
            )
            return
        if len(points) == 0:
            return
        end_ns = int(buf.lines[-1].point_times_ns()[-1])  # the scan's last point
        self.write_point_cloud(points, end_ns, pb.PLATTER_FRAME)

    def _add(self, topic: str, log_time: int, data: bytes) -> None:
        self._check_open()
        if log_time < 0:
            raise RecordingError(
                f"recording {self.path}: negative timestamp {log_time} ns on {topic}; "
                "timestamps are host-clock ns since the Unix epoch"
            )
        channel = self._channels[topic]
        seq = self._sequence.get(channel, 0)
        self._sequence[channel] = seq + 1
        self._writer.add_message(
            channel_id=channel, log_time=log_time, data=data, publish_time=log_time, sequence=seq
        )
        if self._live is not None:
            self._live.publish(topic, channel_schema(topic), data, log_time)
        self._pending += len(data) + 31
        if (
            self._pending >= self._chunk_size
            or time.monotonic() - self._last_flush >= self._flush_interval_s
        ):
            self._flush()

    def _flush(self) -> None:
        try:
            self._writer.flush()  # type: ignore[no-untyped-call]  # finishes the chunk in progress and flushes the stream
        except OSError as exc:
            raise RecordingError(f"cannot write recording {self.path}: {exc}") from exc
        self._pending = 0
        self._last_flush = time.monotonic()


def _check_station(
    kind: str,
    counts_per_revolution: int,
    encoder_direction: int,
    encoder_latency_s: float,
    metadata: Mapping[str, Mapping[str, Any]] | None,
) -> None:
    if not kind:
        raise RecordingError("recording kind must not be empty")
    if int(counts_per_revolution) <= 0:
        raise RecordingError(
            f"counts_per_revolution must be positive, got {counts_per_revolution}"
        )
    if encoder_direction not in (1, -1):
        raise RecordingError(f"encoder_direction must be +1 or -1, got {encoder_direction}")
    if not math.isfinite(encoder_latency_s):
        raise RecordingError(f"encoder_latency_s must be finite, got {encoder_latency_s}")
    for name in metadata or {}:
        if name in RESERVED_METADATA:
            raise RecordingError(
                f"metadata record {name!r} is written by the recorder itself; "
                f"reserved names: {', '.join(RESERVED_METADATA)}"
            )


def _static_transform(t_ns: int, H: Extrinsics) -> bytes:
    """The calibration as ``lidar`` → ``platform``: the pose of P in L."""
    return pb.frame_transform(
        t_ns, pb.LIDAR_FRAME, pb.PLATFORM_FRAME, H.t, H.as_quaternion()
    )


def _recording_from_lines(w: RecordingWriter, buf: _CloudBuffer, max_points: int) -> Recording:
    """An in-memory :class:`Recording` of every k-th point a writer kept, at most
    ``max_points`` points (to reconstruct its cloud: only what is drawn is computed)."""
    lines = buf.lines
    counts = np.array([len(ln) for ln in lines], dtype=np.int64)
    every = slice(None, None, max(1, math.ceil(int(counts.sum()) / max(max_points, 1))))
    enc_t = np.asarray(buf.enc_t, dtype=np.int64)
    enc_c = np.asarray(buf.enc_c, dtype=np.int64)
    order = np.argsort(enc_t, kind="stable")
    return Recording(
        path=w.path,
        kind="",
        metadata={},
        lidar_info=LidarInfo("", "", "", 0.0, 0, 0.0, 0.0, 0.0),
        counts_per_revolution=w._cpr,
        encoder_direction=w._direction,
        encoder_latency_s=w._latency_ns * 1e-9,
        line_timestamp_ns=np.array([ln.timestamp_ns for ln in lines], dtype=np.int64),
        line_index=np.repeat(np.arange(len(lines), dtype=np.int32), counts)[every],
        t_ns=np.concatenate([ln.point_times_ns() for ln in lines])[every],
        azimuth_rad=np.concatenate([np.asarray(ln.azimuth_rad, np.float64) for ln in lines])[
            every
        ],
        range_m=np.concatenate([np.asarray(ln.range_m, np.float64) for ln in lines])[every],
        valid=np.concatenate([np.asarray(ln.valid, bool) for ln in lines])[every],
        intensity=None,
        encoder_t_ns=enc_t[order],
        encoder_count=enc_c[order],
        turntable=[],
        truncated=False,
    )


# --- the recording -------------------------------------------------------------------------
@dataclass(frozen=True, kw_only=True)
class Recording(Scan):
    """A scan read back from an MCAP file (:func:`read_recording`): the engine's
    :class:`~calstation.engine.scan.Scan` (its arrays) with what the file says about it.

    - ``kind``: ``static``, ``spin``, ``cube`` (metadata ``calstation.kind``).
    - ``metadata``: every metadata record, decoded (``calstation``, ``lidar``, ``encoder``,
      ``truth``, ``calibration``, …); ``lidar_info`` the lidar's identity and settings.
    - ``turntable``: the turntable status messages; ``truncated``: the file ended early (a
      writer killed mid-scan) and what it held was read.
    - ``attachments``: attachment name → bytes (``recipe.yaml``).
    """

    kind: str
    metadata: dict[str, dict[str, Any]]
    lidar_info: LidarInfo
    turntable: list[TurntableStatus]
    truncated: bool
    attachments: dict[str, bytes] = field(default_factory=dict)

    @property
    def truth(self) -> Extrinsics | None:
        """The true H of simulated data (metadata ``truth``, keys tx..rz), else None."""
        return self._extrinsics("truth")

    @property
    def calibration(self) -> Extrinsics | None:
        """The H known when the scan was taken (metadata ``calibration``, keys tx..rz, with
        ``source``: ``initial``, ``fine``, ``truth``, …), else None."""
        return self._extrinsics("calibration")

    def _extrinsics(self, name: str) -> Extrinsics | None:
        """The H in metadata record ``name`` (keys tx..rz), None without that record."""
        data = self.metadata.get(name)
        if data is None:
            return None
        try:
            return Extrinsics.from_dict({k: data[k] for k in data if k in _H_KEYS})
        except CalstationError as exc:
            raise RecordingError(
                f"recording {self.path}: metadata '{name}' is invalid: {exc}"
            ) from exc

    @property
    def recipe_text(self) -> str | None:
        """The recipe the scan was taken with (attachment ``recipe.yaml``), if stored."""
        data = self.attachments.get(RECIPE_ATTACHMENT)
        return None if data is None else data.decode("utf-8")

    # --- lines and encoder readings ------------------------------------------------------
    def lines(self) -> Iterator[LidarLine]:
        """The lidar lines, in order, as :class:`~calstation.drivers.LidarLine` (array views)."""
        bounds = self.line_bounds()
        for i in range(self.n_lines):
            a, b = int(bounds[i]), int(bounds[i + 1])
            ts = int(self.line_timestamp_ns[i])
            explicit = self.line_has_offsets is None or bool(self.line_has_offsets[i])
            period = 0.0 if self.line_point_period_ns is None else float(
                self.line_point_period_ns[i]
            )
            yield LidarLine(
                timestamp_ns=ts,
                azimuth_rad=self.azimuth_rad[a:b],
                range_m=self.range_m[a:b],
                valid=self.valid[a:b],
                point_period_ns=period,
                time_offset_ns=(self.t_ns[a:b] - ts) if explicit else None,
                intensity=None if self.intensity is None else self.intensity[a:b],
            )

    def encoder_samples(self) -> list[EncoderSample]:
        """The encoder readings as :class:`~calstation.drivers.EncoderSample`, in time order."""
        return [
            EncoderSample(int(t), int(c))
            for t, c in zip(self.encoder_t_ns.tolist(), self.encoder_count.tolist(), strict=True)
        ]


_H_KEYS = ("tx", "ty", "tz", "rx", "ry", "rz")


# --- reading -------------------------------------------------------------------------------
Buffer = bytes | memoryview


@dataclass
class _Collected:
    """What the reader gathered, message by message, before assembling the arrays.

    Version 1 fills the line lists from one JSON message per line; version 2 from a
    ``LidarLineTiming`` (timing lists) and a ``LaserScan`` (``scan_*`` lists) per line, paired
    in order when assembling.
    """

    metadata: dict[str, dict[str, Any]] = field(default_factory=dict)
    attachments: dict[str, bytes] = field(default_factory=dict)
    v2: bool | None = None
    line_ts: list[int] = field(default_factory=list)
    line_period: list[float] = field(default_factory=list)
    line_count: list[int] = field(default_factory=list)
    line_offsets: list[Buffer | None] = field(default_factory=list)
    azimuth: list[Buffer] = field(default_factory=list)
    range_: list[Buffer] = field(default_factory=list)
    valid: list[Buffer] = field(default_factory=list)
    invalid_range: list[Buffer] = field(default_factory=list)
    intensity: list[Buffer | None] = field(default_factory=list)
    scan_ts: list[int] = field(default_factory=list)
    enc_t: list[int] = field(default_factory=list)
    enc_c: list[int] = field(default_factory=list)
    enc_t_buf: list[Buffer] = field(default_factory=list)
    enc_c_buf: list[Buffer] = field(default_factory=list)
    turntable: list[TurntableStatus] = field(default_factory=list)
    clean: bool = False
    problem: str = ""


def read_recording(path: str | Path) -> Recording:
    """Read a recording written by :class:`RecordingWriter` (format version 1 or 2).

    Raises :class:`RecordingError` (naming the file and the problem) for a missing or non-MCAP
    file, one without the ``calstation`` metadata, or one without lidar lines. A file whose writer
    was killed is read up to its last complete chunk: a :class:`RecordingTruncatedWarning` says
    how much was read, and the result has ``truncated = True``.
    """
    p = Path(path)
    if not p.exists():
        raise RecordingError(f"recording {p} does not exist")
    if not p.is_file():
        raise RecordingError(f"recording {p} is not a file")
    try:
        with open(p, "rb") as f:
            col = _collect(p, f)
    except OSError as exc:
        raise RecordingError(f"cannot read recording {p}: {exc}") from exc
    rec = _assemble(p, col)
    if rec.truncated:
        t_end = (
            (int(rec.t_ns[-1]) - int(rec.line_timestamp_ns[0])) * 1e-9 if rec.n_points else 0.0
        )
        warnings.warn(
            RecordingTruncatedWarning(
                f"recording {p} was not closed cleanly (writer killed?): read {rec.n_lines} "
                f"lines / {len(rec.encoder_t_ns)} encoder samples up to t={t_end:.3f} s after "
                f"the first line ({col.problem})"
            ),
            stacklevel=2,
        )
    return rec


def _collect(p: Path, f: IO[bytes]) -> _Collected:
    from calstation.recordings.mcapscan import MAGIC, Handlers, scan

    col = _Collected()
    data = f.read()
    if len(data) < len(MAGIC) or not data.startswith(MAGIC):
        what = "is empty" if not data else "is not an MCAP file (bad magic bytes)"
        raise RecordingError(f"recording {p} {what}")
    readers: dict[int, Callable[[Buffer], None]] = {}

    def on_channel(channel_id: int, topic: str, encoding: str) -> None:
        if topic in (SCAN_TOPIC, LIDAR_TOPIC) and encoding == "protobuf":
            readers[channel_id] = _line_reader(p, col, topic)
        elif topic in _READ_TOPICS:
            readers[channel_id] = functools.partial(_message, p, col, (topic, encoding))
        else:  # transforms and clouds are derived data: the arrays come from the raw channels
            readers.pop(channel_id, None)

    def on_message(channel_id: int, payload: memoryview) -> None:
        read = readers.get(channel_id)
        if read is not None:
            read(payload)

    def on_metadata(name: str, values: dict[str, str]) -> None:
        col.metadata[name] = _decode_metadata(p, name, values)

    def on_attachment(name: str, payload: bytes) -> None:
        col.attachments[name] = payload

    result = scan(data, Handlers(on_channel, on_message, on_metadata, on_attachment))
    col.clean, col.problem = result.clean, result.problem
    return col


def _decode_metadata(p: Path, name: str, raw: Mapping[str, str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in raw.items():
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value  # written by another tool: keep the plain string
    return out


_READ_TOPICS = (SCAN_TOPIC, LIDAR_TOPIC, ENCODER_TOPIC, TURNTABLE_TOPIC)


def _line_reader(p: Path, col: _Collected, topic: str) -> Callable[[Buffer], None]:
    """The reader of a protobuf ``/lidar/scan`` or ``/lidar/line`` channel: :func:`_message`
    for one topic, its appends bound once (two of these messages per lidar line)."""
    if topic == SCAN_TOPIC:
        decode: Callable[[Buffer], tuple[Any, ...]] = pb.laser_scan_parts
        appends: list[Callable[[Any], None]] = [
            col.scan_ts.append,
            col.range_.append,
            col.intensity.append,
        ]
    else:
        decode = pb.line_timing_parts
        appends = [
            col.line_ts.append,
            col.line_period.append,
            col.line_count.append,
            col.azimuth.append,
            col.valid.append,
            col.line_offsets.append,
            col.invalid_range.append,
        ]

    def read(data: Buffer) -> None:
        if col.v2 is not True:
            if col.v2 is False:
                raise RecordingError(f"recording {p}: {topic} mixes JSON and protobuf messages")
            col.v2 = True
        try:
            parts = decode(data)
        except RecordingError:
            raise
        except (KeyError, TypeError, ValueError) as exc:
            raise RecordingError(f"recording {p}: malformed message on {topic}: {exc!r}") from exc
        for append, value in zip(appends, parts, strict=True):
            append(value)

    return read


def _message(p: Path, col: _Collected, channel: tuple[str, str], data: Buffer) -> None:
    topic, encoding = channel
    try:
        if topic == TURNTABLE_TOPIC:
            col.turntable.append(_turntable_status(json.loads(bytes(data))))
            return
        v2 = encoding == "protobuf"
        if col.v2 is None:
            col.v2 = v2
        elif col.v2 != v2:
            raise RecordingError(f"recording {p}: {topic} mixes JSON and protobuf messages")
        if not v2:
            _message_v1(p, col, topic, json.loads(bytes(data)))
        else:  # the encoder (protobuf lidar lines go to _line_reader)
            t, c = pb.decode_encoder_samples(data)
            if len(t) != len(c) or len(t) % 8:
                raise RecordingError(
                    f"recording {p}: an encoder message has {len(t)} bytes of timestamps for "
                    f"{len(c)} bytes of counts"
                )
            col.enc_t_buf.append(t)
            col.enc_c_buf.append(c)
    except RecordingError:
        raise
    except (KeyError, TypeError, ValueError, binascii.Error) as exc:
        raise RecordingError(f"recording {p}: malformed message on {topic}: {exc!r}") from exc


def _turntable_status(msg: Mapping[str, Any]) -> TurntableStatus:
    return TurntableStatus(
        timestamp_ns=int(msg["timestamp_ns"]),
        state=TurntableState(msg["state"]),
        speed_rpm=float(msg["speed_rpm"]),
        position_rad=None if msg.get("position_rad") is None else float(msg["position_rad"]),
        faults=tuple(str(x) for x in msg.get("faults", ())),
    )


def _message_v1(p: Path, col: _Collected, topic: str, msg: dict[str, Any]) -> None:
    """A version-1 JSON message (base64 arrays) of ``/lidar/line`` or ``/encoder/count``."""
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
    arrays: dict[str, np.dtype[Any]] = {
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


@dataclass
class _Lines:
    """The per-line and per-point arrays of a recording, before the :class:`Recording`."""

    line_ts: NDArray[np.int64]
    periods: NDArray[np.float64]
    counts: NDArray[np.int64]
    azimuth: NDArray[np.float64]
    range_m: NDArray[np.float64]
    valid: NDArray[np.bool_]
    offsets: list[Buffer | None]
    intensity: list[Buffer | None]
    intensity_dtype: np.dtype[Any]


def _assemble(p: Path, col: _Collected) -> Recording:
    meta = col.metadata
    incomplete = "" if col.clean else f" (the file is incomplete, writer killed? {col.problem})"
    info, lidar_info, (cpr, direction, latency) = _check_metadata(p, meta, incomplete)
    lines = _lines_v2(p, col) if col.v2 else _lines_v1(col)
    if len(lines.counts) == 0:
        raise RecordingError(f"recording {p} contains no lidar lines{incomplete}")
    n_lines = len(lines.counts)
    counts, line_ts = lines.counts, lines.line_ts
    line_index = np.repeat(np.arange(n_lines, dtype=np.int32), counts)
    starts = np.zeros(n_lines, dtype=np.int64)
    np.cumsum(counts[:-1], out=starts[1:])
    has_offsets = np.array([o is not None for o in lines.offsets], dtype=bool)
    t_ns = _point_times(lines, line_index, starts, has_offsets)
    intensity: NDArray[np.float64] | None = None
    if any(x is not None for x in lines.intensity):
        parts = [
            np.frombuffer(x, dtype=lines.intensity_dtype)
            if x is not None
            else np.full(int(n), np.nan, dtype=lines.intensity_dtype)
            for x, n in zip(lines.intensity, counts, strict=True)
        ]
        intensity = np.concatenate(parts).astype(np.float64)
    enc_t, enc_c = _encoder_arrays(col)
    return Recording(
        path=p,
        kind=str(info.get("kind", "")),
        metadata=meta,
        lidar_info=lidar_info,
        counts_per_revolution=cpr,
        encoder_direction=direction,
        encoder_latency_s=latency,
        line_timestamp_ns=line_ts,
        line_index=line_index,
        t_ns=t_ns,
        azimuth_rad=lines.azimuth,
        range_m=lines.range_m,
        valid=lines.valid,
        intensity=intensity,
        encoder_t_ns=enc_t,
        encoder_count=enc_c,
        turntable=col.turntable,
        truncated=not col.clean,
        line_point_period_ns=lines.periods,
        line_has_offsets=has_offsets,
        attachments=col.attachments,
    )


def _check_metadata(
    p: Path, meta: dict[str, dict[str, Any]], incomplete: str
) -> tuple[dict[str, Any], LidarInfo, tuple[int, int, float]]:
    """The ``calstation`` record, the lidar info and (counts/rev, direction, latency)."""
    if "calstation" not in meta:
        raise RecordingError(
            f"recording {p} has no 'calstation' metadata: not a calstation recording{incomplete}"
        )
    info = meta["calstation"]
    version = info.get("format_version")
    if not isinstance(version, int) or version > FORMAT_VERSION or version < 1:
        raise RecordingError(
            f"recording {p} has format_version {version!r}; this calstation reads "
            f"versions 1..{FORMAT_VERSION}"
        )
    for name in ("lidar", "encoder"):
        if name not in meta:
            raise RecordingError(f"recording {p} has no {name!r} metadata record{incomplete}")
    try:
        lidar_info = LidarInfo.from_dict(meta["lidar"])
    except (KeyError, TypeError, ValueError) as exc:
        raise RecordingError(f"recording {p}: metadata 'lidar' is invalid: {exc!r}") from exc
    enc = meta["encoder"]
    try:
        cpr = int(enc["counts_per_revolution"])
        direction = int(enc["direction"])
        latency = float(enc.get("latency_s", 0.0))
    except (KeyError, TypeError, ValueError) as exc:
        raise RecordingError(f"recording {p}: metadata 'encoder' is invalid: {exc!r}") from exc
    if cpr <= 0 or direction not in (1, -1):
        raise RecordingError(
            f"recording {p}: metadata 'encoder' has counts_per_revolution={cpr}, "
            f"direction={direction} (expected > 0 and ±1)"
        )
    return info, lidar_info, (cpr, direction, latency)


def _lines_v1(col: _Collected) -> _Lines:
    return _Lines(
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


def _lines_v2(p: Path, col: _Collected) -> _Lines:
    """Pair each line's LaserScan with its LidarLineTiming and check their sizes."""
    n = min(len(col.line_ts), len(col.scan_ts))
    if col.clean and len(col.line_ts) != len(col.scan_ts):
        raise RecordingError(
            f"recording {p} has {len(col.scan_ts)} LaserScan messages on {SCAN_TOPIC} for "
            f"{len(col.line_ts)} line timings on {LIDAR_TOPIC}"
        )
    # a killed writer may have written one message of the last pair: it is dropped
    line_ts = np.asarray(col.line_ts[:n], dtype=np.int64)
    scan_ts = np.asarray(col.scan_ts[:n], dtype=np.int64)
    counts = np.asarray(col.line_count[:n], dtype=np.int64)
    if np.any(line_ts != scan_ts):
        i = int(np.flatnonzero(line_ts != scan_ts)[0])
        raise RecordingError(
            f"recording {p}: lidar line {i} has LaserScan time {scan_ts[i]} ns but line timing "
            f"time {line_ts[i]} ns"
        )
    sizes: dict[str, tuple[list[Buffer], int]] = {
        "azimuth_rad": (col.azimuth, pb.AZIMUTH_DTYPE.itemsize),
        "valid": (col.valid, pb.VALID_DTYPE.itemsize),
        "ranges": (col.range_, pb.RANGE_DTYPE.itemsize),
    }
    for name, (bufs, itemsize) in sizes.items():
        got = np.fromiter((len(b) for b in bufs[:n]), dtype=np.int64, count=n)
        bad = np.flatnonzero(got != counts * itemsize)
        if bad.size:
            i = int(bad[0])
            raise RecordingError(
                f"recording {p}: lidar line {i} field {name} has {got[i]} bytes, expected "
                f"{counts[i] * itemsize} for {counts[i]} points"
            )
    valid = _concat(col.valid[:n], pb.VALID_DTYPE).view(bool)
    range_m = _concat(col.range_[:n], pb.RANGE_DTYPE)
    invalid = np.frombuffer(b"".join(col.invalid_range[:n]), pb.RANGE_DTYPE)
    n_invalid = len(valid) - int(np.count_nonzero(valid))
    if len(invalid) == n_invalid:
        range_m[~valid] = invalid  # the raw ranges of invalid returns (NaN in the LaserScan)
    elif len(invalid):
        raise RecordingError(
            f"recording {p}: {len(invalid)} raw ranges of invalid returns for {n_invalid} "
            "invalid returns"
        )
    return _Lines(
        line_ts=line_ts,
        periods=np.asarray(col.line_period[:n], dtype=np.float64),
        counts=counts,
        azimuth=_concat(col.azimuth[:n], pb.AZIMUTH_DTYPE).view(np.float64),
        range_m=range_m,
        valid=valid,
        offsets=col.line_offsets[:n],
        intensity=col.intensity[:n],
        intensity_dtype=pb.INTENSITY_DTYPE,
    )


def _concat(parts: list[Buffer], dtype: np.dtype[Any]) -> NDArray[Any]:
    """One writable array of the packed arrays ``parts`` (a single copy)."""
    if not parts:
        return np.zeros(0, dtype=dtype)
    return np.concatenate([np.frombuffer(b, dtype=dtype) for b in parts])


def _point_times(
    lines: _Lines,
    line_index: NDArray[np.int32],
    starts: NDArray[np.int64],
    has_offsets: NDArray[np.bool_],
) -> NDArray[np.int64]:
    """(M,) host time of every point: explicit offsets where a line has them, else its period."""
    counts, line_ts = lines.counts, lines.line_ts
    if not has_offsets.any() and np.all(counts == counts[0]) and np.all(
        lines.periods == lines.periods[0]
    ):  # the usual scan: every line alike, so one row of offsets serves them all
        row = np.round(np.arange(counts[0]) * lines.periods[0]).astype(np.int64)
        same: NDArray[np.int64] = (line_ts[:, None] + row[None, :]).reshape(-1)
        return same
    if has_offsets.all():
        offsets = np.frombuffer(b"".join(o or b"" for o in lines.offsets), V1_TIME_OFFSET_DTYPE)
        if len(offsets) == len(line_index):
            return np.repeat(line_ts, counts) + offsets
    within = np.arange(len(line_index), dtype=np.int64) - np.repeat(starts, counts)
    t_ns = np.repeat(line_ts, counts) + np.round(
        within * np.repeat(lines.periods, counts)
    ).astype(np.int64)
    for i in np.flatnonzero(has_offsets):
        off = np.frombuffer(lines.offsets[i] or b"", dtype=V1_TIME_OFFSET_DTYPE)
        if len(off) != counts[i]:
            raise RecordingError(
                f"lidar line {i} has {len(off)} time offsets for {counts[i]} points"
            )
        t_ns[starts[i] : starts[i] + counts[i]] = line_ts[i] + off
    return t_ns


def _encoder_arrays(col: _Collected) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    if col.enc_t_buf:
        enc_t = np.frombuffer(b"".join(col.enc_t_buf), pb.TIME_DTYPE).astype(np.int64)
        enc_c = np.frombuffer(b"".join(col.enc_c_buf), pb.TIME_DTYPE).astype(np.int64)
    else:
        enc_t = np.asarray(col.enc_t, dtype=np.int64)
        enc_c = np.asarray(col.enc_c, dtype=np.int64)
    if len(enc_t) > 1 and np.any(np.diff(enc_t) < 0):
        order = np.argsort(enc_t, kind="stable")
        enc_t, enc_c = enc_t[order], enc_c[order]
    return enc_t, enc_c
