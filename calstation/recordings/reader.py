"""Reading a recording: :func:`read_recording` turns an MCAP file written by
:class:`~calstation.recordings.writer.RecordingWriter` into a
:class:`~calstation.recordings.recorded.Recording` with flat numpy arrays (one entry per point).

Version 2 (protobuf messages, ``docs/recording-format.md``) is decoded here; version 1 (JSON
messages with base64 arrays) in :mod:`calstation.recordings.v1`. The file is read front to back,
record by record (:mod:`calstation.recordings.mcapscan`), never trusting its summary, so that a
file whose writer was killed is read up to its last complete chunk.
"""

from __future__ import annotations

import binascii
import functools
import json
import struct
import warnings
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import IO, Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from calstation.drivers import LidarInfo, TurntableState, TurntableStatus
from calstation.errors import RecordingError
from calstation.recordings import messages as pb
from calstation.recordings.channels import (
    ENCODER_TOPIC,
    FORMAT_VERSION,
    LIDAR_TOPIC,
    SCAN_TOPIC,
    TURNTABLE_TOPIC,
)
from calstation.recordings.collected import Buffer, Collected, Lines
from calstation.recordings.metadata import decode_metadata
from calstation.recordings.recorded import Recording
from calstation.recordings.v1 import V1_TIME_OFFSET_DTYPE, collect_message_v1, lines_v1

S = TypeVar("S", bound=np.generic)


class RecordingTruncatedWarning(UserWarning):
    """A recording was not closed cleanly (its writer was killed); it was read up to its last
    complete chunk."""


def read_recording(path: str | Path) -> Recording:
    """Read a recording written by :class:`~calstation.recordings.writer.RecordingWriter`
    (format version 1 or 2).

    Raises :class:`RecordingError` (naming the file and the problem) for a missing or non-MCAP
    file, one without the ``calstation`` metadata, or one without lidar lines; for a file
    damaged since its writer finished it (a CRC that does not match, with the footer present);
    for one that asks for more than :class:`~calstation.recordings.mcapscan.ReadLimits` allow
    (a decompression bomb); and for one whose line times go backwards or whose encoder jumps
    faster than a turntable turns (:func:`check_timing`). A file whose writer was killed is read
    up to its last complete chunk: a :class:`RecordingTruncatedWarning` says how much was read,
    and the result has ``truncated = True``.
    """
    p = Path(path)
    if not p.exists():
        raise RecordingError(f"recording {p} does not exist")
    if not p.is_file():
        raise RecordingError(f"recording {p} is not a file")
    try:
        with open(p, "rb") as f:
            col = _collect(p, f)
        rec = _assemble(p, col)
        check_timing(p, rec)
    except OSError as exc:
        raise RecordingError(f"cannot read recording {p}: {exc}") from exc
    except RecordingError as exc:
        if str(p) in str(exc):
            raise
        raise RecordingError(f"recording {p}: {exc}") from exc
    except (ValueError, KeyError, IndexError, TypeError, OverflowError, struct.error) as exc:
        # whatever else malformed content makes the decoders meet: named, never a traceback
        raise RecordingError(
            f"recording {p} is malformed: {type(exc).__name__}: {exc}"
        ) from exc
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


def _collect(p: Path, f: IO[bytes]) -> Collected:
    from calstation.recordings.mcapscan import MAGIC, Handlers, Refused, scan

    col = Collected()
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

    def on_metadata(name: str, values: dict[str, str]) -> None:
        col.metadata[name] = decode_metadata(p, name, values)

    def on_attachment(name: str, payload: bytes) -> None:
        col.attachments[name] = payload

    try:
        result = scan(data, Handlers(on_channel, _no_message, on_metadata, on_attachment,
                                     routes=readers))
    except Refused as exc:
        raise RecordingError(f"recording {p} is refused: {exc}") from None
    if not result.clean and result.complete:
        raise RecordingError(
            f"recording {p} is damaged: {result.problem}. The file ends with its footer, so "
            "its writer finished it: it was damaged since (on the disk, or in a copy); read "
            "its shared copy or a backup instead"
        )
    col.clean, col.problem = result.clean, result.problem
    col.spread_parts()
    return col


_READ_TOPICS = (SCAN_TOPIC, LIDAR_TOPIC, ENCODER_TOPIC, TURNTABLE_TOPIC)


def _no_message(channel_id: int, payload: memoryview) -> None:
    """Every message goes by its channel's route (the channels the reader does not read have
    none)."""


def _line_reader(p: Path, col: Collected, topic: str) -> Callable[[Buffer], None]:
    """The reader of a protobuf ``/lidar/scan`` or ``/lidar/line`` channel: :func:`_message`
    for one topic (two of these messages per lidar line), each message's parts kept as one
    tuple (:meth:`Collected.spread_parts` spreads them over the line lists)."""
    if topic == SCAN_TOPIC:
        # Any: the parts of one message, of their own types
        decode: Callable[[Buffer], tuple[Any, ...]] = pb.laser_scan_parts
        keep = col.scan_parts.append
    else:
        decode = pb.line_timing_parts
        keep = col.timing_parts.append

    def read(data: Buffer) -> None:
        if col.v2 is not True:
            if col.v2 is False:
                raise RecordingError(f"recording {p}: {topic} mixes JSON and protobuf messages")
            col.v2 = True
        try:
            keep(decode(data))
        except RecordingError:
            raise
        except (KeyError, TypeError, ValueError) as exc:
            raise RecordingError(f"recording {p}: malformed message on {topic}: {exc!r}") from exc

    return read


def _message(p: Path, col: Collected, channel: tuple[str, str], data: Buffer) -> None:
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
            collect_message_v1(p, col, topic, json.loads(bytes(data)))
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


def _turntable_status(msg: Mapping[str, Any]) -> TurntableStatus:  # Any: the message's JSON
    return TurntableStatus(
        timestamp_ns=int(msg["timestamp_ns"]),
        state=TurntableState(msg["state"]),
        speed_rpm=float(msg["speed_rpm"]),
        position_rad=None if msg.get("position_rad") is None else float(msg["position_rad"]),
        faults=tuple(str(x) for x in msg.get("faults", ())),
    )


def _assemble(p: Path, col: Collected) -> Recording:
    meta = col.metadata
    incomplete = "" if col.clean else f" (the file is incomplete, writer killed? {col.problem})"
    info, lidar_info, (cpr, direction, latency) = _check_metadata(p, meta, incomplete)
    lines = _lines_v2(p, col) if col.v2 else lines_v1(col)
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
    p: Path, meta: dict[str, dict[str, Any]], incomplete: str  # Any: decoded JSON
) -> tuple[dict[str, Any], LidarInfo, tuple[int, int, float]]:  # Any: as given
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


def _lines_v2(p: Path, col: Collected) -> Lines:
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
    return Lines(
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


def _concat(parts: list[Buffer], dtype: np.dtype[S]) -> NDArray[S]:
    """One writable array of the packed arrays ``parts`` (a single copy)."""
    if not parts:
        return np.zeros(0, dtype=dtype)
    return np.concatenate([np.frombuffer(b, dtype=dtype) for b in parts])


def _point_times(
    lines: Lines,
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


MAX_TURN_RATE = 10.0
"""Turns per second no turntable reaches (600 rpm: five times the fastest a recipe may turn):
an encoder that jumps faster than this between two readings wrapped, or the data are damaged."""

READING_JITTER_S = 0.02
"""How late a reading's time stamp may be against its count (a driver's thread or a USB or CAN
frame delayed on a loaded station PC): two readings 1.7 ms apart by their stamps may hold counts
taken 20 ms apart. 0.2 turns at :data:`MAX_TURN_RATE`; a wrapped 32-bit counter jumps by far
more."""


def check_timing(p: Path, rec: Recording) -> None:
    """:class:`RecordingError` naming the reading when the lines' times go backwards or the
    encoder jumps between two readings faster than :data:`MAX_TURN_RATE` (a raw counter that
    wrapped, as a 32-bit count does): either would make a wrong cloud without a word."""
    line_t = rec.line_timestamp_ns
    back = np.flatnonzero(np.diff(line_t) < 0)
    if back.size:
        i = int(back[0]) + 1
        raise RecordingError(
            f"recording {p}: lidar line {i} is stamped {(line_t[i - 1] - line_t[i]) * 1e-6:,.3f}"
            f" ms before line {i - 1}: the line times go backwards (a clock that jumped?), and "
            "calstation reads a scan only in time order"
        )
    t, c, cpr = rec.encoder_t_ns, rec.encoder_count, rec.counts_per_revolution
    if len(t) < 2:
        return
    dt = np.diff(t).astype(np.float64) * 1e-9
    jump = np.abs(np.diff(c).astype(np.float64))
    # and the stamps' jitter, and 0.1° of reading noise
    allowed = MAX_TURN_RATE * (dt + READING_JITTER_S) * cpr + max(2.0, cpr / 3600.0)
    fast = np.flatnonzero(jump > allowed)
    if fast.size:
        i = int(fast[0]) + 1
        raise RecordingError(
            f"recording {p}: encoder reading {i} is {jump[i - 1]:,.0f} counts "
            f"({jump[i - 1] / cpr:,.3g} turns) from reading {i - 1}, {dt[i - 1] * 1e3:,.3f} ms "
            f"before it: faster than any turntable turns ({MAX_TURN_RATE * 60:.0f} rpm). A raw "
            "counter that wrapped (a 32-bit count?) or damaged data; the counts must be "
            "unwrapped (docs/recording-format.md)"
        )


def _encoder_arrays(col: Collected) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
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
