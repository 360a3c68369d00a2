"""Text line logs in: one row per lidar line (its time, the mount angle, its ranges) as an
:class:`~calstation.recordings.imported.ImportedScan`.

The columns are named by :class:`LineLogColumns`; the delimiter (comma, semicolon, tab or
spaces) is found from the header. The ranges are either many columns matched by a pattern, in
their order in the file (``r*``), or one column holding them all separated by spaces or
semicolons. Point i of a line has the calstation azimuth ``first + i·step`` (frame L, DESIGN §2)
and is measured ``i·point_period`` after the line's time. An empty or non-numeric cell, or a
range outside [``range_min``, ``range_max``], is an invalid return (kept, marked).
"""

from __future__ import annotations

import csv
import fnmatch
import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from calstation.drivers import LidarInfo, LidarLine
from calstation.errors import RecordingImportError
from calstation.recordings.imported import ImportedScan, file_digest, line_rate

TIME_UNITS = {"s": 10**9, "ms": 10**6, "us": 10**3, "ns": 1}
RANGE_UNITS = {"m": 1.0, "mm": 1e-3}


@dataclass(frozen=True)
class LineLogColumns:
    """How to read a line log: column names and units (see the module)."""

    time: str
    angle: str
    ranges: str
    azimuths: str
    """``FIRST:STEP`` in degrees: the azimuth α of point 0 and the step to the next point."""
    time_unit: str = "s"
    range_unit: str = "m"
    point_period_s: float = 0.0
    range_min_m: float = 0.0
    range_max_m: float = math.inf
    hold: bool = False
    """The angle holds for its whole line (stop-and-go) rather than being sampled at its time."""


def read_line_log(
    path: Path,
    columns: LineLogColumns,
    *,
    angle_unit: str = "rad",
    progress: Callable[[int, int], None] | None = None,
) -> ImportedScan:
    """Read the line log ``path`` as described by ``columns``; ``angle_unit`` is that of the
    angle column. Raises :class:`RecordingImportError` naming the file, the row, the column and
    what was found."""
    path = Path(path)
    _azimuths(columns.azimuths)  # a malformed azimuth spec is the first thing said
    if columns.time_unit not in TIME_UNITS:
        raise RecordingImportError(f"--time-unit {columns.time_unit!r}: use one of "
                                   f"{', '.join(TIME_UNITS)}")
    if columns.range_unit not in RANGE_UNITS:
        raise RecordingImportError(f"--range-unit {columns.range_unit!r}: use one of "
                                   f"{', '.join(RANGE_UNITS)}")
    lines, angles = _read_lines(path, columns, progress)
    notes = []
    order = sorted(range(len(lines)), key=lambda i: lines[i].timestamp_ns)
    if order != list(range(len(lines))):
        lines = [lines[i] for i in order]
        angles = [angles[i] for i in order]
        notes.append("rows out of time order: sorted by time")
    invalid = sum(int(len(ln) - np.count_nonzero(ln.valid)) for ln in lines)
    if invalid:
        notes.append(f"{invalid} returns invalid (empty, not a number or outside the range "
                     "limits): kept, marked invalid")
    angle_t, values = _angle_samples(lines, angles, columns.hold)
    lidar, source = _provenance(path, columns, lines, angle_unit)
    return ImportedScan(lines, angle_t, values, angle_unit, lidar, source, notes)


def _read_lines(
    path: Path, columns: LineLogColumns, progress: Callable[[int, int], None] | None
) -> tuple[list[LidarLine], list[float]]:
    """Each row as a lidar line, with its angle; the first problem as an error."""
    first, step = _azimuths(columns.azimuths)
    header, rows = _table(path)
    where = f"{path}"
    t_col = _column(header, columns.time, "--time", where)
    a_col = _column(header, columns.angle, "--angle", where)
    r_cols, split = _range_columns(header, columns.ranges, where)
    scale = RANGE_UNITS[columns.range_unit]
    lines: list[LidarLine] = []
    angles: list[float] = []
    n_points = None
    for k, row in enumerate(rows):
        rowno = k + 2  # 1-based, after the header
        if not any(cell.strip() for cell in row):
            continue
        if len(row) < len(header):
            raise RecordingImportError(f"{where}: row {rowno}: {len(row)} cells for "
                                       f"{len(header)} columns")
        t_ns = _time_ns(row[t_col], columns.time_unit, f"{where}: row {rowno}: column "
                        f"{columns.time!r}")
        angles.append(_float(row[a_col], f"{where}: row {rowno}: column {columns.angle!r}"))
        cells = (re.split(r"[\s;]+", row[r_cols[0]].strip()) if split
                 else [row[c] for c in r_cols])
        rng = np.array([_range(c) for c in cells], dtype=np.float64) * scale
        if n_points is None:
            n_points = len(rng)
        elif len(rng) != n_points:
            raise RecordingImportError(
                f"{where}: row {rowno}: mismatched lengths: {len(rng)} ranges in "
                f"{columns.ranges!r}, the first line had {n_points}"
            )
        valid = np.isfinite(rng) & (rng >= columns.range_min_m) & (rng <= columns.range_max_m)
        lines.append(LidarLine(
            timestamp_ns=t_ns,
            azimuth_rad=np.radians(first + step * np.arange(len(rng))),
            range_m=np.where(np.isfinite(rng), rng, np.nan),
            valid=valid,
            point_period_ns=columns.point_period_s * 1e9,
        ))
        if progress is not None:
            progress(k + 1, len(rows))
    if not lines:
        raise RecordingImportError(f"{where}: no lines (the file has a header and no rows)")
    return lines, angles


def _angle_samples(
    lines: list[LidarLine], angles: list[float], hold: bool
) -> tuple[np.ndarray, np.ndarray]:
    """The angle readings in time: one per line at its time, or (``hold``) held over each
    line, from its first return to its last; one value per time."""
    if hold:
        t = [v for ln in lines for v in (int(ln.point_times_ns().min()),
                                         int(ln.point_times_ns().max()))]
        a = [v for v in angles for _ in range(2)]
    else:
        t, a = [ln.timestamp_ns for ln in lines], angles
    angle_t = np.asarray(t, np.int64)
    values = np.asarray(a, np.float64)
    keep = np.ones(len(angle_t), bool)
    keep[:-1] = angle_t[1:] != angle_t[:-1]  # one value per time
    return angle_t[keep], values[keep]


def _provenance(
    path: Path, columns: LineLogColumns, lines: list[LidarLine], angle_unit: str
) -> tuple[LidarInfo, dict[str, object]]:
    """The lidar as the log describes it, and where the recording's data came from."""
    _, step = _azimuths(columns.azimuths)
    n = len(lines[0])
    lidar = LidarInfo(
        vendor="line log import",
        model=path.name,
        serial="",
        fov_rad=abs(math.radians(step)) * max(n - 1, 0),
        points_per_line=n,
        line_rate_hz=line_rate([ln.timestamp_ns for ln in lines]),
        range_min_m=columns.range_min_m,
        range_max_m=columns.range_max_m if math.isfinite(columns.range_max_m) else 1e9,
        extra={"azimuths_deg": columns.azimuths, "point_period_s": columns.point_period_s},
    )
    source = {
        "tool": "calstation import csv",
        "log": file_digest(path),
        "scan": f"{path.name}: columns {columns.ranges!r}",
        "angle": f"{path.name}: column {columns.angle!r}",
        "time": f"column {columns.time!r} ({columns.time_unit})",
        "angle_unit": angle_unit,
        "angle_held_per_line": columns.hold,
        "azimuths_deg": columns.azimuths,
        "range_unit": columns.range_unit,
    }
    return lidar, source


def _table(path: Path) -> tuple[list[str], list[list[str]]]:
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise RecordingImportError(f"cannot read line log {path}: {exc}") from exc
    head = text.splitlines()[0] if text.strip() else ""
    if not head:
        raise RecordingImportError(f"{path} is empty: no header row, no lines")
    delimiter = next((d for d in (",", ";", "\t") if d in head), None)
    if delimiter is None:
        rows = [re.split(r"\s+", ln.strip()) for ln in text.splitlines() if ln.strip()]
    else:
        rows = list(csv.reader(text.splitlines(), delimiter=delimiter))
    header = [h.strip() for h in rows[0]]
    return header, rows[1:]


def _column(header: list[str], name: str, option: str, where: str) -> int:
    if name not in header:
        raise RecordingImportError(
            f"{option} {name!r}: {where} has no such column; its columns: {', '.join(header)}"
        )
    return header.index(name)


def _range_columns(header: list[str], pattern: str, where: str) -> tuple[list[int], bool]:
    """The range columns (by pattern, in file order), or the one column holding all ranges."""
    if pattern in header and not any(ch in pattern for ch in "*?["):
        return [header.index(pattern)], True
    cols = [i for i, h in enumerate(header) if fnmatch.fnmatchcase(h, pattern)]
    if not cols:
        raise RecordingImportError(
            f"--ranges {pattern!r}: {where} has no matching column; its columns: "
            f"{', '.join(header[:12])}{' …' if len(header) > 12 else ''}"
        )
    return cols, False


def _azimuths(text: str) -> tuple[float, float]:
    try:
        first, step = (float(v) for v in text.split(":"))
    except ValueError:
        raise RecordingImportError(
            f"--azimuths {text!r}: expected FIRST:STEP in degrees, e.g. -45:0.25"
        ) from None
    if step == 0 or not (math.isfinite(first) and math.isfinite(step)):
        raise RecordingImportError(f"--azimuths {text!r}: the step must be a non-zero number")
    return first, step


def _time_ns(cell: str, unit: str, where: str) -> int:
    try:  # Decimal: epoch seconds as floats would lose the nanoseconds
        return int(Decimal(cell.strip()) * TIME_UNITS[unit])
    except (InvalidOperation, ValueError):
        raise RecordingImportError(f"{where}: {cell!r} is not a time") from None


def _float(cell: str, where: str) -> float:
    try:
        value = float(cell)
    except ValueError:
        raise RecordingImportError(f"{where}: {cell!r} is not a number: the angle is missing") \
            from None
    if not math.isfinite(value):
        raise RecordingImportError(f"{where}: the angle is {cell!r}")
    return value


def _range(cell: str) -> float:
    try:
        return float(cell)
    except ValueError:
        return math.nan
