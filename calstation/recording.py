"""Recordings: each scan written to MCAP while it is acquired, and read back as numpy arrays.

The format is documented in ``docs/recording-format.md``. In short:

- MCAP, chunked (~1 MiB per chunk), zstd-compressed; the file is flushed after every chunk (and at
  least every second) so that a writer killed mid-scan loses at most the chunk in progress.
- Schema encoding ``jsonschema``, message encoding ``json`` (Foxglove and ``mcap cat`` open it).
  Bulk arrays are base64 strings of little-endian arrays (``"contentEncoding": "base64"``).
- Channels ``/lidar/line``, ``/encoder/count``, ``/turntable/status``; message ``log_time`` is the
  host-clock time of the data.
- Metadata records ``calstation``, ``lidar``, ``encoder`` (and ``truth`` for simulated data, or any
  other name); each value is JSON-encoded (MCAP metadata values are strings).
- The recipe text is the attachment ``recipe.yaml``.

:func:`read_recording` returns a :class:`Recording` with flat numpy arrays (one entry per point).
"""

from __future__ import annotations

import base64
import binascii
import contextlib
import json
import math
import os
import struct
import threading
import time
import warnings
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .drivers import EncoderSample, LidarInfo, LidarLine, TurntableState, TurntableStatus
from .errors import CalstationError, RecordingError
from .frames import Extrinsics, counts_to_angle
from .recipe import LoadedRecipe

FORMAT_VERSION: int = 1
"""Version of the recording layout (channels, schemas, metadata) described in the docs."""

LIDAR_TOPIC = "/lidar/line"
ENCODER_TOPIC = "/encoder/count"
TURNTABLE_TOPIC = "/turntable/status"
RECIPE_ATTACHMENT = "recipe.yaml"
RESERVED_METADATA = ("calstation", "lidar", "encoder")

DEFAULT_CHUNK_SIZE = 1 << 20
"""Uncompressed bytes per chunk: a crash loses at most about this much of the scan."""
DEFAULT_FLUSH_INTERVAL_S = 1.0
"""A chunk is also closed and flushed when this much wall time passed since the last flush."""

# dtypes of the base64 arrays (little-endian), part of the format
AZIMUTH_DTYPE = np.dtype("<f8")
RANGE_DTYPE = np.dtype("<f4")
VALID_DTYPE = np.dtype("u1")
INTENSITY_DTYPE = np.dtype("<f4")
TIME_OFFSET_DTYPE = np.dtype("<i8")


class RecordingTruncatedWarning(UserWarning):
    """A recording was not closed cleanly (its writer was killed); it was read up to its last
    complete chunk."""


# --- schemas -------------------------------------------------------------------------------
def _b64(dtype: str, unit: str, what: str) -> dict[str, Any]:
    return {
        "type": "string",
        "contentEncoding": "base64",
        "description": f"{what}: little-endian {dtype}[count], {unit}",
    }


LIDAR_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "calstation.LidarLine",
    "description": "One line of a 2D line scanner in its own polar coordinates (frame L).",
    "type": "object",
    "properties": {
        "timestamp_ns": {
            "type": "integer",
            "description": "host-clock time of the first point, ns since the Unix epoch",
        },
        "point_period_ns": {
            "type": "number",
            "description": "time between consecutive points, ns (point i at timestamp + i·period)",
        },
        "count": {"type": "integer", "description": "number of points in the line"},
        "azimuth_rad": _b64("float64", "rad", "azimuth α (0 = +Y_L, positive toward +X_L)"),
        "range_m": _b64("float32", "m", "range ρ (meaningless where valid = 0)"),
        "valid": _b64("uint8", "0/1", "1 = valid return"),
        "time_offset_ns": _b64(
            "int64", "ns", "optional per-point time offsets from timestamp_ns (overrides period)"
        ),
        "intensity": _b64("float32", "device units", "optional intensity"),
    },
    "required": ["timestamp_ns", "point_period_ns", "count", "azimuth_rad", "range_m", "valid"],
}

ENCODER_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "calstation.EncoderSamples",
    "description": "A batch of encoder readings, oldest first.",
    "type": "object",
    "properties": {
        "timestamp_ns": {
            "type": "array",
            "items": {"type": "integer"},
            "description": "host-clock time of each reading, ns since the Unix epoch",
        },
        "count": {
            "type": "array",
            "items": {"type": "integer"},
            "description": "unwrapped signed encoder count of each reading",
        },
    },
    "required": ["timestamp_ns", "count"],
}

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


def _b64encode(values: ArrayLike, dtype: np.dtype[Any]) -> str:
    arr = np.ascontiguousarray(values, dtype=dtype)
    return base64.b64encode(arr.tobytes()).decode("ascii")


class RecordingWriter:
    """Writes one scan to an MCAP file while it is acquired. A context manager.

    ``kind`` says what the scan is (``"static"``, ``"spin"``, ``"cube"`` or free text);
    ``lidar_info``, ``counts_per_revolution``, ``encoder_direction`` (+1/−1) and
    ``encoder_latency_s`` (encoder time minus lidar time, s) describe the station and are stored as
    metadata, with ``station_id``, the recipe's name and sha256 (its text becomes the attachment
    ``recipe.yaml``) and any further ``metadata`` records (name → mapping, e.g. ``"truth"``).

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
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        flush_interval_s: float = DEFAULT_FLUSH_INTERVAL_S,
    ) -> None:
        from mcap.writer import CompressionType, Writer

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
        # encode everything before creating the file, so bad metadata leaves no file behind
        encoded = {name: _encode_metadata(name, data) for name, data in records.items()}

        self.path = Path(path)
        self._lock = threading.RLock()
        self._chunk_size = int(chunk_size)
        self._flush_interval_s = float(flush_interval_s)
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
            self._lidar_channel = self._channel(LIDAR_TOPIC, LIDAR_SCHEMA)
            self._encoder_channel = self._channel(ENCODER_TOPIC, ENCODER_SCHEMA)
            self._turntable_channel = self._channel(TURNTABLE_TOPIC, TURNTABLE_SCHEMA)
            self._file.flush()
        except OSError as exc:
            self._closed = True
            self._file.close()
            raise RecordingError(f"cannot write recording {self.path}: {exc}") from exc

    # --- public API ----------------------------------------------------------------------
    def write_line(self, line: LidarLine) -> None:
        """Append one lidar line (stamped on the host clock)."""
        n = len(line)
        msg: dict[str, Any] = {
            "timestamp_ns": int(line.timestamp_ns),
            "point_period_ns": float(line.point_period_ns),
            "count": n,
            "azimuth_rad": _b64encode(line.azimuth_rad, AZIMUTH_DTYPE),
            "range_m": _b64encode(line.range_m, RANGE_DTYPE),
            "valid": _b64encode(np.asarray(line.valid, dtype=bool), VALID_DTYPE),
        }
        if line.time_offset_ns is not None:
            msg["time_offset_ns"] = _b64encode(line.time_offset_ns, TIME_OFFSET_DTYPE)
        if line.intensity is not None:
            msg["intensity"] = _b64encode(line.intensity, INTENSITY_DTYPE)
        with self._lock:
            self._add(self._lidar_channel, int(line.timestamp_ns), msg)
            self.lines_written += 1
            self.points_written += n

    def write_encoder(self, samples: Iterable[EncoderSample]) -> None:
        """Append encoder readings (oldest first), batched into one message."""
        batch = list(samples)
        if not batch:
            return
        msg = {
            "timestamp_ns": [int(s.timestamp_ns) for s in batch],
            "count": [int(s.count) for s in batch],
        }
        with self._lock:
            self._add(self._encoder_channel, msg["timestamp_ns"][0], msg)
            self.encoder_samples_written += len(batch)

    def write_turntable(self, status: TurntableStatus) -> None:
        """Append one turntable status report."""
        with self._lock:
            self._add(self._turntable_channel, int(status.timestamp_ns), status.as_dict())

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
        (``error``: the exception's type and message), so the partial scan says why it ended."""
        if exc is not None and not self._closed:
            with contextlib.suppress(Exception):
                self.add_metadata("aborted", {"error": f"{type(exc).__name__}: {exc}"})
        self.close()

    # --- internals -----------------------------------------------------------------------
    def _check_open(self) -> None:
        if self._closed:
            raise RecordingError(f"recording {self.path} is already closed")

    def _write_metadata(self, name: str, data: Mapping[str, Any]) -> None:
        self._writer.add_metadata(name, _encode_metadata(name, data))

    def _channel(self, topic: str, schema: dict[str, Any]) -> int:
        schema_id = self._writer.register_schema(
            name=str(schema["title"]),
            encoding="jsonschema",
            data=json.dumps(schema).encode("utf-8"),
        )
        return self._writer.register_channel(
            topic=topic, message_encoding="json", schema_id=schema_id
        )

    def _add(self, channel: int, log_time: int, msg: Mapping[str, Any]) -> None:
        self._check_open()
        if log_time < 0:
            raise RecordingError(
                f"recording {self.path}: negative timestamp {log_time} ns on {channel}; "
                "timestamps are host-clock ns since the Unix epoch"
            )
        data = json.dumps(msg, separators=(",", ":")).encode("utf-8")
        seq = self._sequence.get(channel, 0)
        self._sequence[channel] = seq + 1
        self._writer.add_message(
            channel_id=channel, log_time=log_time, data=data, publish_time=log_time, sequence=seq
        )
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


# --- the recording -------------------------------------------------------------------------
@dataclass(frozen=True)
class Recording:
    """A scan read back from disk, as flat arrays (one entry per point, valid or not).

    Times are host-clock ns since the Unix epoch; angles radians; ranges metres. Arrays:

    - ``line_timestamp_ns`` (L,): time of the first point of each line.
    - ``line_index`` (M,) int32: the line of each point; ``t_ns`` (M,): time of each point.
    - ``azimuth_rad``, ``range_m``, ``valid``, ``intensity`` (M,) (intensity None if absent).
    - ``encoder_t_ns``, ``encoder_count`` (K,): encoder readings in time order.
    - ``line_point_period_ns`` (L,) and ``line_has_offsets`` (L,): each line's point period and
      whether it carried explicit per-point offsets (None when built by hand: :meth:`lines` then
      gives every line explicit offsets).
    - ``attachments``: attachment name → bytes (``recipe.yaml``).
    """

    path: Path
    kind: str
    metadata: dict[str, dict[str, Any]]
    lidar_info: LidarInfo
    counts_per_revolution: int
    encoder_direction: int
    encoder_latency_s: float
    line_timestamp_ns: NDArray[np.int64]
    line_index: NDArray[np.int32]
    t_ns: NDArray[np.int64]
    azimuth_rad: NDArray[np.float64]
    range_m: NDArray[np.float64]
    valid: NDArray[np.bool_]
    intensity: NDArray[np.float64] | None
    encoder_t_ns: NDArray[np.int64]
    encoder_count: NDArray[np.int64]
    turntable: list[TurntableStatus]
    truncated: bool
    line_point_period_ns: NDArray[np.float64] | None = None
    line_has_offsets: NDArray[np.bool_] | None = None
    attachments: dict[str, bytes] = field(default_factory=dict)

    # --- summaries -----------------------------------------------------------------------
    @property
    def n_lines(self) -> int:
        """Number of lidar lines L."""
        return len(self.line_timestamp_ns)

    @property
    def n_points(self) -> int:
        """Number of points M (valid or not)."""
        return len(self.t_ns)

    @property
    def truth(self) -> Extrinsics | None:
        """The true H of simulated data (metadata ``truth``, keys tx..rz), else None."""
        data = self.metadata.get("truth")
        if data is None:
            return None
        try:
            return Extrinsics.from_dict({k: data[k] for k in data if k in _H_KEYS})
        except CalstationError as exc:
            raise RecordingError(
                f"recording {self.path}: metadata 'truth' is invalid: {exc}"
            ) from exc

    @property
    def recipe_text(self) -> str | None:
        """The recipe the scan was taken with (attachment ``recipe.yaml``), if stored."""
        data = self.attachments.get(RECIPE_ATTACHMENT)
        return None if data is None else data.decode("utf-8")

    # --- geometry ------------------------------------------------------------------------
    def platter_angle(self, t_ns: ArrayLike) -> NDArray[np.float64]:
        """Platter angle φ (rad) at host-clock times ``t_ns`` (lidar time base), shape of input.

        The encoder counts are interpolated linearly in time, after shifting the encoder's
        timestamps by ``encoder_latency_s`` (encoder time minus lidar time) onto the lidar's time
        base, then converted with the encoder direction and counts per revolution. φ is unwrapped
        (it keeps growing over several turns). Times outside the encoder's span give NaN — except
        when every reading has the same count (a platter at rest), which holds for all times.
        Raises :class:`RecordingError` if the recording has no encoder readings.
        """
        t = np.asarray(t_ns, dtype=np.int64)
        if len(self.encoder_t_ns) == 0:
            raise RecordingError(
                f"recording {self.path} has no encoder readings: the platter angle is unknown"
            )
        counts = self.encoder_count.astype(np.float64)
        if np.all(self.encoder_count == self.encoder_count[0]):
            phi0 = counts_to_angle(counts[0], self.counts_per_revolution, self.encoder_direction)
            return np.full(t.shape, float(phi0))
        t0 = int(self.encoder_t_ns[0])
        latency_ns = round(self.encoder_latency_s * 1e9)
        enc_s = (self.encoder_t_ns - t0 - latency_ns).astype(np.float64) * 1e-9
        query_s = (t - t0).astype(np.float64) * 1e-9
        c = np.interp(query_s, enc_s, counts, left=np.nan, right=np.nan)
        return counts_to_angle(c, self.counts_per_revolution, self.encoder_direction)

    def points_lidar(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Valid points with a known platter angle: ((N, 3) in frame L, metres; (N,) φ, rad).

        Invalid returns and points outside the encoder's time span (φ NaN) are left out.
        """
        idx = np.flatnonzero(self.valid)
        phi = self.platter_angle(self.t_ns[idx])
        keep = np.isfinite(phi)
        if not keep.all():
            idx, phi = idx[keep], phi[keep]
        rng = self.range_m[idx]
        az = self.azimuth_rad[idx]
        # same as frames.polar_to_lidar, filled in place (this runs on millions of points)
        p_L = np.zeros((len(idx), 3))
        np.multiply(rng, np.sin(az), out=p_L[:, 0])
        np.multiply(rng, np.cos(az), out=p_L[:, 1])
        return p_L, phi

    def line_bounds(self) -> NDArray[np.int64]:
        """(L+1,) offsets: the points of line i are ``[bounds[i], bounds[i+1])``."""
        counts = np.bincount(self.line_index, minlength=self.n_lines)
        bounds = np.zeros(self.n_lines + 1, dtype=np.int64)
        np.cumsum(counts, out=bounds[1:])
        return bounds

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
class _ExactReader:
    """A file wrapper whose ``read(n)`` returns n bytes or raises ``EndOfFile`` (so a record cut
    off by a killed writer is detected as incomplete instead of being parsed short)."""

    def __init__(self, f: IO[bytes]) -> None:
        self._f = f
        self.at_boundary = False

    def read(self, n: int = -1) -> bytes:
        from mcap.exceptions import EndOfFile

        data = self._f.read(n)
        if n >= 0 and len(data) != n:
            # nothing at all where a record's opcode should be: the file ends between records
            self.at_boundary = n == 1 and not data
            raise EndOfFile()
        return data


class _Incomplete(Exception):
    """The file ends (or is damaged) before a record is complete."""


@dataclass
class _Collected:
    metadata: dict[str, dict[str, Any]] = field(default_factory=dict)
    attachments: dict[str, bytes] = field(default_factory=dict)
    line_ts: list[int] = field(default_factory=list)
    line_period: list[float] = field(default_factory=list)
    line_count: list[int] = field(default_factory=list)
    line_offsets: list[bytes | None] = field(default_factory=list)
    azimuth: list[bytes] = field(default_factory=list)
    range_: list[bytes] = field(default_factory=list)
    valid: list[bytes] = field(default_factory=list)
    intensity: list[bytes | None] = field(default_factory=list)
    enc_t: list[int] = field(default_factory=list)
    enc_c: list[int] = field(default_factory=list)
    turntable: list[TurntableStatus] = field(default_factory=list)
    clean: bool = False
    problem: str = ""


def read_recording(path: str | Path) -> Recording:
    """Read a recording written by :class:`RecordingWriter`.

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
    from mcap.exceptions import EndOfFile, InvalidMagic, McapError
    from mcap.records import Attachment, Channel, Chunk, Footer, Message, Metadata
    from mcap.stream_reader import StreamReader, breakup_chunk

    col = _Collected()
    head = f.read(8)
    if len(head) < 8 or head != b"\x89MCAP0\r\n":
        what = "is empty" if not head else "is not an MCAP file (bad magic bytes)"
        raise RecordingError(f"recording {p} {what}")
    f.seek(0)
    channels: dict[int, str] = {}
    exact = _ExactReader(f)
    reader = StreamReader(exact, emit_chunks=True)  # type: ignore[arg-type]
    records = reader.records
    footer_seen = False
    while True:
        try:
            record = next(records)
        except StopIteration:
            col.clean = footer_seen
            if not footer_seen:
                col.problem = "the file ends without the MCAP footer"
            break
        except (EndOfFile, struct.error, InvalidMagic, McapError, ValueError, MemoryError) as exc:
            if not isinstance(exc, (EndOfFile, struct.error)):
                col.problem = f"damaged record: {exc}"
            elif exact.at_boundary:
                col.problem = "the file ends after a complete record, without the MCAP footer"
            else:
                col.problem = "the file ends inside a record, which was dropped"
            break
        if isinstance(record, Chunk):
            try:
                inner = breakup_chunk(record, validate_crc=True)
            except Exception as exc:  # zstd / CRC / parse errors: a damaged chunk
                col.problem = f"damaged chunk: {exc}"
                break
            for r in inner:
                if isinstance(r, Channel):
                    channels[r.id] = r.topic
                elif isinstance(r, Message):
                    _message(p, col, channels.get(r.channel_id, ""), r.data)
        elif isinstance(record, Metadata):
            col.metadata[record.name] = _decode_metadata(p, record.name, record.metadata)
        elif isinstance(record, Attachment):
            col.attachments[record.name] = bytes(record.data)
        elif isinstance(record, Channel):
            channels[record.id] = record.topic
        elif isinstance(record, Footer):
            footer_seen = True
        elif isinstance(record, Message):  # unchunked file (another writer)
            _message(p, col, channels.get(record.channel_id, ""), record.data)
    return col


def _decode_metadata(p: Path, name: str, raw: Mapping[str, str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in raw.items():
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value  # written by another tool: keep the plain string
    return out


def _message(p: Path, col: _Collected, topic: str, data: bytes) -> None:
    if topic not in (LIDAR_TOPIC, ENCODER_TOPIC, TURNTABLE_TOPIC):
        return
    try:
        msg = json.loads(data)
        if topic == LIDAR_TOPIC:
            n = int(msg["count"])
            col.line_ts.append(int(msg["timestamp_ns"]))
            col.line_period.append(float(msg["point_period_ns"]))
            col.line_count.append(n)
            az = base64.b64decode(msg["azimuth_rad"])
            rg = base64.b64decode(msg["range_m"])
            va = base64.b64decode(msg["valid"])
            off = base64.b64decode(msg["time_offset_ns"]) if "time_offset_ns" in msg else None
            it = base64.b64decode(msg["intensity"]) if "intensity" in msg else None
            sizes = {
                "azimuth_rad": (len(az), n * AZIMUTH_DTYPE.itemsize),
                "range_m": (len(rg), n * RANGE_DTYPE.itemsize),
                "valid": (len(va), n * VALID_DTYPE.itemsize),
            }
            if off is not None:
                sizes["time_offset_ns"] = (len(off), n * TIME_OFFSET_DTYPE.itemsize)
            if it is not None:
                sizes["intensity"] = (len(it), n * INTENSITY_DTYPE.itemsize)
            for name, (got, want) in sizes.items():
                if got != want:
                    raise RecordingError(
                        f"recording {p}: lidar line {len(col.line_ts) - 1} field {name} has "
                        f"{got} bytes, expected {want} for {n} points"
                    )
            col.azimuth.append(az)
            col.range_.append(rg)
            col.valid.append(va)
            col.line_offsets.append(off)
            col.intensity.append(it)
        elif topic == ENCODER_TOPIC:
            ts, cs = msg["timestamp_ns"], msg["count"]
            if len(ts) != len(cs):
                raise RecordingError(
                    f"recording {p}: an encoder message has {len(ts)} timestamps for "
                    f"{len(cs)} counts"
                )
            col.enc_t.extend(int(t) for t in ts)
            col.enc_c.extend(int(c) for c in cs)
        else:
            col.turntable.append(
                TurntableStatus(
                    timestamp_ns=int(msg["timestamp_ns"]),
                    state=TurntableState(msg["state"]),
                    speed_rpm=float(msg["speed_rpm"]),
                    position_rad=(
                        None if msg.get("position_rad") is None else float(msg["position_rad"])
                    ),
                    faults=tuple(str(x) for x in msg.get("faults", ())),
                )
            )
    except RecordingError:
        raise
    except (KeyError, TypeError, ValueError, binascii.Error) as exc:
        raise RecordingError(f"recording {p}: malformed message on {topic}: {exc!r}") from exc


def _assemble(p: Path, col: _Collected) -> Recording:
    meta = col.metadata
    incomplete = "" if col.clean else f" (the file is incomplete, writer killed? {col.problem})"
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
    if not col.line_ts:
        raise RecordingError(f"recording {p} contains no lidar lines{incomplete}")

    counts = np.asarray(col.line_count, dtype=np.int64)
    n_lines = len(counts)
    line_ts = np.asarray(col.line_ts, dtype=np.int64)
    periods = np.asarray(col.line_period, dtype=np.float64)
    azimuth = np.frombuffer(b"".join(col.azimuth), dtype=AZIMUTH_DTYPE).astype(np.float64)
    range_m = np.frombuffer(b"".join(col.range_), dtype=RANGE_DTYPE).astype(np.float64)
    valid = np.frombuffer(b"".join(col.valid), dtype=VALID_DTYPE).astype(bool)
    line_index = np.repeat(np.arange(n_lines, dtype=np.int32), counts)
    starts = np.zeros(n_lines, dtype=np.int64)
    np.cumsum(counts[:-1], out=starts[1:])
    within = np.arange(len(line_index), dtype=np.int64) - starts[line_index]
    t_ns = line_ts[line_index] + np.round(within * periods[line_index]).astype(np.int64)
    has_offsets = np.array([o is not None for o in col.line_offsets], dtype=bool)
    if has_offsets.any():
        for i in np.flatnonzero(has_offsets):
            off = np.frombuffer(col.line_offsets[i] or b"", dtype=TIME_OFFSET_DTYPE)
            t_ns[starts[i] : starts[i] + counts[i]] = line_ts[i] + off
    intensity: NDArray[np.float64] | None = None
    if any(x is not None for x in col.intensity):
        parts = [
            np.frombuffer(x, dtype=INTENSITY_DTYPE)
            if x is not None
            else np.full(int(n), np.nan, dtype=INTENSITY_DTYPE)
            for x, n in zip(col.intensity, counts, strict=True)
        ]
        intensity = np.concatenate(parts).astype(np.float64)

    enc_t = np.asarray(col.enc_t, dtype=np.int64)
    enc_c = np.asarray(col.enc_c, dtype=np.int64)
    if len(enc_t) > 1 and np.any(np.diff(enc_t) < 0):
        order = np.argsort(enc_t, kind="stable")
        enc_t, enc_c = enc_t[order], enc_c[order]

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
        azimuth_rad=azimuth,
        range_m=range_m,
        valid=valid,
        intensity=intensity,
        encoder_t_ns=enc_t,
        encoder_count=enc_c,
        turntable=col.turntable,
        truncated=not col.clean,
        line_point_period_ns=periods,
        line_has_offsets=has_offsets,
        attachments=col.attachments,
    )
