"""Writing a recording: :class:`RecordingWriter` puts each scan in an MCAP file while it is
acquired, and sends every message to the process's live sink (the live view) too.

The layout is :mod:`calstation.recordings.channels` (channels and schemas),
:mod:`calstation.recordings.metadata` (metadata records) and ``docs/recording-format.md``:
MCAP, chunked (~1 MiB per chunk), zstd-compressed, flushed after every chunk (and at least every
second) so that a writer killed mid-scan loses at most the chunk in progress.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import threading
import time
import warnings
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Protocol

import numpy as np
from numpy.typing import ArrayLike

from calstation.clock import Clock, HostClock
from calstation.drivers import EncoderSample, LidarInfo, LidarLine, TurntableStatus
from calstation.engine.frames import Extrinsics, counts_to_angle
from calstation.engine.scan import Scan
from calstation.errors import RecordingError
from calstation.recordings import messages as pb
from calstation.recordings.channels import (
    CHANNELS,
    CLOUD_TOPIC,
    ENCODER_TOPIC,
    FORMAT_VERSION,
    LIDAR_TOPIC,
    PLATTER_TF_TOPIC,
    RECIPE_ATTACHMENT,
    RESERVED_METADATA,
    SCAN_TOPIC,
    STATIC_TF_TOPIC,
    TURNTABLE_TOPIC,
    channel_schema,
)
from calstation.recordings.metadata import (
    RecipeInfo,
    calibration_record,
    encode_metadata,
    station_records,
)

DEFAULT_CHUNK_SIZE = 1 << 20
"""Uncompressed bytes per chunk: a crash loses at most about this much of the scan."""
DEFAULT_FLUSH_INTERVAL_S = 1.0
"""A chunk is also closed and flushed when this much wall time passed since the last flush."""
DEFAULT_CLOUD_POINTS = 300_000
"""At most this many points in the reconstructed cloud written at the end of a scan."""


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

    ``clock`` is the station's clock, the one its drivers stamp the data with (a
    :class:`~calstation.clock.HostClock` when not given; the simulator's or a replay's own clock
    otherwise): the file's creation time (metadata ``created_ns``, the recipe attachment) and
    the calibration's ``/tf_static`` are stamped on it, so that every time in the file is on
    one clock and the calibration precedes the data.

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
        recipe: RecipeInfo | None = None,
        metadata: Mapping[str, Mapping[str, object]] | None = None,
        calibration: Extrinsics | None = None,
        calibration_source: str = "",
        live: LiveSink | None = None,
        clock: Clock | None = None,
        cloud_points: int = DEFAULT_CLOUD_POINTS,
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        flush_interval_s: float = DEFAULT_FLUSH_INTERVAL_S,
    ) -> None:
        from mcap.writer import CompressionType, Writer

        _check_station(kind, counts_per_revolution, encoder_direction, encoder_latency_s, metadata)
        created_ns = int((clock if clock is not None else HostClock()).now_ns())
        records: dict[str, Mapping[str, object]] = {
            **station_records(
                kind, station_id, recipe, created_ns, lidar_info,
                (counts_per_revolution, encoder_direction, encoder_latency_s),
            ),
            **dict(metadata or {}),
        }
        if calibration is not None:
            records["calibration"] = calibration_record(calibration, calibration_source)
        # encode everything before creating the file, so bad metadata leaves no file behind
        encoded = {name: encode_metadata(name, data) for name, data in records.items()}

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
        # the data section's CRC lets a reader tell damage done since the file was finished
        self._writer = Writer(self._file, chunk_size=1 << 62, compression=CompressionType.ZSTD,
                              enable_data_crcs=True)
        self._closed = False
        self._pending = 0
        self._last_flush = time.monotonic()
        self._sequence: dict[int, int] = {}
        self._channels: dict[str, int] = {}
        self.lines_written = 0
        self.points_written = 0
        self.encoder_samples_written = 0
        self._start(encoded, recipe, created_ns)
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

    def add_metadata(self, name: str, data: Mapping[str, object]) -> None:
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
    def _start(
        self, encoded: Mapping[str, dict[str, str]], recipe: RecipeInfo | None, created_ns: int
    ) -> None:
        """Write the file's header, its metadata records, the recipe (the attachment
        ``recipe.yaml``) and the channels, and flush them to the operating system."""
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

    def _check_open(self) -> None:
        if self._closed:
            raise RecordingError(f"recording {self.path} is already closed")

    def _write_metadata(self, name: str, data: Mapping[str, object]) -> None:
        self._writer.add_metadata(name, encode_metadata(name, data))

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
            scan = _scan_from_lines(self, buf, self._cloud_points)
            points = reconstruct(scan, H)
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
    metadata: Mapping[str, Mapping[str, object]] | None,
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


def _scan_from_lines(w: RecordingWriter, buf: _CloudBuffer, max_points: int) -> Scan:
    """An in-memory :class:`~calstation.engine.scan.Scan` of every k-th point a writer kept, at
    most ``max_points`` points (to reconstruct its cloud: only what is drawn is computed)."""
    lines = buf.lines
    counts = np.array([len(ln) for ln in lines], dtype=np.int64)
    every = slice(None, None, max(1, math.ceil(int(counts.sum()) / max(max_points, 1))))
    enc_t = np.asarray(buf.enc_t, dtype=np.int64)
    enc_c = np.asarray(buf.enc_c, dtype=np.int64)
    order = np.argsort(enc_t, kind="stable")
    return Scan(
        path=w.path,
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
    )


