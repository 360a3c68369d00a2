"""Recordings made from data calstation did not acquire: lines and angle samples in, a version-2
recording out, written whole or not at all.

The importers (:mod:`calstation.recordings.rosbag` for ROS bags,
:mod:`calstation.recordings.linelog` for text line logs) turn their source into
:class:`ImportedScan` — calstation lidar lines (frame L, DESIGN §2) and angle samples on the
lines' clock — and :func:`write_imported` writes it with
:class:`~calstation.recordings.writer.RecordingWriter`, so ``reconstruct``, ``calibrate`` and
``verify`` read it like any station's recording. The angle becomes encoder readings:
``count = round(angle / full turn · counts_per_revolution)``, unwrapped, with the encoder's
latency 0 (the samples are already on the lines' clock).
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calstation.atomic import atomic_output
from calstation.clock import SimClock
from calstation.drivers import EncoderSample, LidarInfo, LidarLine
from calstation.errors import RecordingImportError

if TYPE_CHECKING:
    from calstation.recordings.messages import SchemaData
    from calstation.recordings.writer import RecordingWriter

ANGLE_UNITS = ("deg", "rad", "counts")
"""Units of an imported angle: degrees, radians, or encoder counts (``counts_per_revolution``
of them per turn)."""
FINE_COUNTS_PER_REVOLUTION = 1 << 32
"""The grid an angle in degrees or radians is stored on when no ``counts_per_revolution`` is
given: 1.5·10⁻⁹ rad, 3 nm at 2 m, far below any lidar's noise."""
KINDS = ("spin", "static", "cube")
ENCODER_BATCH = 256
"""Angle samples per ``/encoder/count`` message."""


@dataclass(frozen=True)
class ImportedScan:
    """A scan read from another format, ready to write.

    ``lines`` in time order, each stamped on one clock; ``angle_t_ns`` (K,) and ``angle`` (K,)
    the mount's angle samples on the same clock, in ``angle_unit``. ``lidar`` describes the
    sensor; ``source`` says where the data came from (the ``import`` metadata record); ``notes``
    are what the import had to decide or leave out, said to the user.
    """

    lines: list[LidarLine]
    angle_t_ns: NDArray[np.int64]
    angle: NDArray[np.float64]
    angle_unit: str
    lidar: LidarInfo
    source: Mapping[str, object]
    notes: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class ImportResult:
    """What :func:`write_imported` wrote: the file, its numbers and the import's notes."""

    path: Path
    lines: int
    points: int
    valid: int
    angle_samples: int
    counts_per_revolution: int
    lines_outside_angle: int
    notes: list[str]


COUNTS_BITS = (8, 16, 24, 32, 64)
"""Widths of the raw counters ``--counts-bits`` unwraps."""


def angle_counts(
    values: ArrayLike, unit: str, counts_per_revolution: int | None, what: str,
    counts_bits: int | None = None,
) -> tuple[NDArray[np.int64], int]:
    """Angle samples as unwrapped integer encoder counts, and the counts per revolution.

    ``unit`` is one of :data:`ANGLE_UNITS`; ``counts`` needs ``counts_per_revolution``; for
    degrees and radians it is the grid (default :data:`FINE_COUNTS_PER_REVOLUTION`), so give
    the encoder's own to keep its counts exactly. ``counts_bits``: the counts are a raw counter
    of that many bits (signed or not), which wraps at 2^bits: unwrapped first. A jump of more
    than half a turn between two samples is taken as a wrap of an angle reported modulo one
    turn and unwrapped; a jump of more than a turn and a half (a counter that wrapped, or a
    gap no unwrapping can bridge) is refused, naming the sample. ``what`` names the angle's
    source in errors.
    """
    if unit not in ANGLE_UNITS:
        raise RecordingImportError(
            f"{what}: angle unit {unit!r} is not one of {', '.join(ANGLE_UNITS)}"
        )
    v = np.asarray(values, dtype=np.float64)
    if not np.all(np.isfinite(v)):
        bad = int(np.flatnonzero(~np.isfinite(v))[0])
        raise RecordingImportError(f"{what}: angle sample {bad} is {v[bad]}, not a number")
    if counts_per_revolution is not None and int(counts_per_revolution) <= 0:
        raise RecordingImportError(
            f"{what}: counts per revolution must be positive, got {counts_per_revolution}"
        )
    if counts_bits is not None and (unit != "counts" or counts_bits not in COUNTS_BITS):
        raise RecordingImportError(
            f"{what}: --counts-bits is the width of a raw counter: "
            + ("one of " + ", ".join(map(str, COUNTS_BITS)) if unit == "counts"
               else "it needs --angle-unit counts")
        )
    if unit == "counts":
        if counts_per_revolution is None:
            raise RecordingImportError(
                f"{what}: an angle in encoder counts needs --counts-per-rev N (counts per turn)"
            )
        cpr = int(counts_per_revolution)
        counts = np.round(v)
        if counts_bits is not None and len(counts) > 1:
            modulus = float(2**counts_bits)
            steps = np.diff(counts)
            steps = (steps + modulus / 2) % modulus - modulus / 2
            counts = counts[0] + np.concatenate([[0.0], np.cumsum(steps)])
    else:
        cpr = int(counts_per_revolution or FINE_COUNTS_PER_REVOLUTION)
        full = 360.0 if unit == "deg" else 2.0 * math.pi
        counts = np.round(v / full * cpr)
    if len(counts) > 1:  # unwrap: a step of more than half a turn is a wrap
        steps = np.diff(counts)
        wraps = np.round(steps / cpr)
        _refuse_impossible_jumps(steps, wraps, cpr, unit, what)
        counts = counts - np.concatenate([[0.0], np.cumsum(wraps)]) * cpr
    return counts.astype(np.int64), cpr


def _refuse_impossible_jumps(steps: NDArray[np.float64], wraps: NDArray[np.float64], cpr: int,
                             unit: str, what: str) -> None:
    """An angle reported modulo one turn wraps by one turn; more than that between two samples
    is a raw counter that wrapped (2^bits, not a turn) or a gap no unwrapping can bridge."""
    bad = np.flatnonzero(np.abs(wraps) > 1)
    if not bad.size:
        return
    i = int(bad[0]) + 1
    turns = steps[i - 1] / cpr
    hint = ("a raw counter that wrapped: give --counts-bits N (its width in bits)"
            if unit == "counts" else "samples missing there, or an angle that is not one")
    raise RecordingImportError(
        f"{what}: angle sample {i} is {turns:+,.2f} turns from sample {i - 1}; an angle "
        f"reported modulo one turn wraps by one turn, so this is {hint}"
    )


def file_digest(path: Path) -> dict[str, object]:
    """Name, size and sha256 of a source file (or of each file of a bag folder)."""
    files = sorted(q for q in path.rglob("*") if q.is_file()) if path.is_dir() else [path]
    out = []
    for f in files:
        h = hashlib.sha256()
        with f.open("rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
        out.append({"name": str(f), "bytes": f.stat().st_size, "sha256": h.hexdigest()})
    return {"path": str(path), "files": out}


def write_imported(
    scan: ImportedScan,
    out: Path,
    *,
    kind: str = "spin",
    counts_per_revolution: int | None = None,
    direction: int = 1,
    station_id: str = "",
    progress: Callable[[int, int], None] | None = None,
    counts_bits: int | None = None,
) -> ImportResult:
    """Write ``scan`` to the version-2 recording ``out``: all of it, or nothing.

    The file is written beside ``out`` under a temporary name and renamed at the end
    (:func:`calstation.atomic.atomic_output`), so a failure (or Ctrl-C, or a full disk) leaves
    no half-written file and never touches an existing ``out``; a folder, device or FIFO named
    as ``out`` is refused before anything is written.
    ``kind`` (:data:`KINDS`) is the recording's kind; ``counts_per_revolution`` and
    ``direction`` (+1/−1: the sign of the platter angle φ relative to the imported angle)
    go to the ``encoder`` record. ``progress(done, total)`` is told about the lines written.
    ``counts_bits``: the angle is a raw counter of that many bits (:func:`angle_counts`).
    """
    from calstation.recordings.writer import RecordingWriter

    what = scan.source.get("angle", "the angle")
    if kind not in KINDS:
        raise RecordingImportError(f"kind {kind!r} is not one of {', '.join(KINDS)}")
    if direction not in (1, -1):
        raise RecordingImportError(f"direction must be 1 or -1, got {direction}")
    if not scan.lines:
        raise RecordingImportError(f"{scan.source.get('scan', 'the scan')}: no lidar lines")
    if len(scan.angle_t_ns) == 0:
        raise RecordingImportError(f"{what}: no angle samples")
    counts, cpr = angle_counts(scan.angle, scan.angle_unit, counts_per_revolution, str(what),
                               counts_bits)
    order = np.argsort(scan.angle_t_ns, kind="stable")
    enc_t, enc_c = np.asarray(scan.angle_t_ns, np.int64)[order], counts[order]
    outside = _lines_outside(scan.lines, enc_t, enc_c)
    if outside == len(scan.lines):
        line_t = np.array([ln.timestamp_ns for ln in scan.lines], dtype=np.int64)
        raise RecordingImportError(
            f"no line of {scan.source.get('scan', 'the scan')} lies within the time span of "
            f"{what} ({_span(enc_t)}; lines {_span(line_t)}): are they stamped on one clock?"
        )
    notes = list(scan.notes)
    if outside:
        notes.append(
            f"{outside} of {len(scan.lines)} lines reach outside the time span of {what}: "
            "their points there have no angle and are left out of reconstructions"
        )
    source = {**scan.source, "counts_per_revolution": cpr, "direction": direction,
              "notes": notes}
    with atomic_output(out, "recording") as tmp, RecordingWriter(
        tmp,
        kind=kind,
        lidar_info=scan.lidar,
        counts_per_revolution=cpr,
        encoder_direction=direction,
        encoder_latency_s=0.0,
        station_id=station_id,
        metadata={"import": source},
        clock=SimClock(min(int(scan.lines[0].timestamp_ns), int(enc_t[0]))),
        live=_NoLive(),
    ) as writer:
        points, valid = _write_scan(writer, scan.lines, enc_t, enc_c, progress)
    return ImportResult(Path(out), len(scan.lines), points, valid, len(enc_t), cpr, outside,
                        notes)


def _write_scan(writer: RecordingWriter, lines: Sequence[LidarLine], enc_t: NDArray[np.int64],
                enc_c: NDArray[np.int64], progress: Callable[[int, int], None] | None,
                ) -> tuple[int, int]:
    """Write ``lines`` and the encoder readings between them in time order; (points, valid)."""
    points = valid = 0
    k = 0
    for i, line in enumerate(lines):
        end = int(line.point_times_ns().max())
        while k < len(enc_t) and enc_t[k] <= end:
            j = min(k + ENCODER_BATCH, int(np.searchsorted(enc_t, end, "right")))
            writer.write_encoder(
                EncoderSample(int(t), int(c)) for t, c in zip(enc_t[k:j], enc_c[k:j], strict=True)
            )
            k = j
        writer.write_line(line)
        points += len(line)
        valid += int(np.count_nonzero(line.valid))
        if progress is not None:
            progress(i + 1, len(lines))
    for j in range(k, len(enc_t), ENCODER_BATCH):
        writer.write_encoder(
            EncoderSample(int(t), int(c))
            for t, c in zip(enc_t[j : j + ENCODER_BATCH], enc_c[j : j + ENCODER_BATCH],
                            strict=True)
        )
    return points, valid


class _NoLive:
    """An import is not a live scan: nothing goes to the process's live view."""

    def publish(self, topic: str, schema: SchemaData, data: bytes, log_time_ns: int) -> None:
        """Drop the message."""


def _lines_outside(lines: Sequence[LidarLine], enc_t: NDArray[np.int64],
                   enc_c: NDArray[np.int64]) -> int:
    """How many lines have points outside the angle samples' time span (a constant angle holds
    at all times, as :meth:`calstation.engine.scan.Scan.platter_angle` does)."""
    if np.all(enc_c == enc_c[0]):
        return 0
    lo, hi = int(enc_t[0]), int(enc_t[-1])
    n = 0
    for line in lines:
        t = line.point_times_ns()
        if t.min() < lo or t.max() > hi:
            n += 1
    return n


def _span(t: NDArray[np.int64]) -> str:
    return f"{int(t.min()) * 1e-9:.3f} s … {int(t.max()) * 1e-9:.3f} s since the epoch"


def line_rate(line_t_ns: Sequence[int]) -> float:
    """Lines per second from the lines' times (median interval), 0 if unknown."""
    t = np.asarray(line_t_ns, dtype=np.int64)
    if len(t) < 2:
        return 0.0
    dt = np.diff(t)
    dt = dt[dt > 0]
    return float(1e9 / np.median(dt)) if len(dt) else 0.0
